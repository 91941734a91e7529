//! Soft travel limits and a maximum step, checked before any motion command is sent.
//!
//! They guard against a wrong unit or a bad job (50 mm typed for 50 µm) independently of the
//! controller's own limits: the drivers refuse the move with [`HwError::Limit`] and nothing
//! moves.
//!
//! `max_step_um` has one meaning everywhere: the largest distance of any single move,
//! absolute or relative, from where the stage was last commanded to be (its target; the
//! drivers ask the controller for it: GCS `MOV?`, GRBL's last target or idle position).
//! The plan checks it between a job's frames at submit; the drivers check every move.

use super::HwError;
use crate::text::short_um as um;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TravelLimits {
    /// Lowest allowed target, µm.
    pub min_um: f64,
    /// Highest allowed target, µm.
    pub max_um: f64,
    /// Longest allowed single move (absolute or relative) from the last target, µm.
    pub max_step_um: f64,
}

impl TravelLimits {
    pub fn new(min_um: f64, max_um: f64, max_step_um: f64) -> Result<TravelLimits, String> {
        let l = TravelLimits {
            min_um,
            max_um,
            max_step_um,
        };
        l.validate()?;
        Ok(l)
    }

    /// Config sanity: finite, ordered, positive step.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.min_um.is_finite() && self.max_um.is_finite() && self.max_step_um.is_finite()) {
            return Err(format!(
                "travel limits must be finite numbers: min {} µm, max {} µm, max step {} µm",
                self.min_um, self.max_um, self.max_step_um
            ));
        }
        if self.min_um >= self.max_um {
            return Err(format!(
                "min_um ({}) must be below max_um ({})",
                um(self.min_um),
                um(self.max_um)
            ));
        }
        if self.max_step_um <= 0.0 {
            return Err(format!(
                "max_step_um must be positive, not {}",
                um(self.max_step_um)
            ));
        }
        Ok(())
    }

    /// An absolute target inside the travel (the step is not checked: see [`check_move`]).
    ///
    /// [`check_move`]: TravelLimits::check_move
    pub fn check_abs(&self, device: &str, target_um: f64) -> Result<(), HwError> {
        let refuse = |reason: String| HwError::Limit {
            device: device.to_string(),
            target_um,
            reason,
        };
        if !target_um.is_finite() {
            return Err(refuse("the target is not a finite number".into()));
        }
        if target_um < self.min_um || target_um > self.max_um {
            return Err(refuse(format!(
                "outside the soft travel limits [{}, {}] µm",
                um(self.min_um),
                um(self.max_um)
            )));
        }
        Ok(())
    }

    /// A move from the last target `from_um` to `target_um`: inside the travel, and no
    /// longer than the maximum step.
    pub fn check_move(&self, device: &str, from_um: f64, target_um: f64) -> Result<(), HwError> {
        self.check_abs(device, target_um)?;
        let dist = (target_um - from_um).abs();
        // A NaN distance (an unknown start) is also refused.
        if dist.is_nan() || dist > self.max_step_um {
            return Err(HwError::Limit {
                device: device.to_string(),
                target_um,
                reason: format!(
                    "a move of {} µm from the last target {} µm exceeds the maximum step of {} µm",
                    um(dist),
                    um(from_um),
                    um(self.max_step_um)
                ),
            });
        }
        Ok(())
    }

    /// A relative move from the last target `from_um`; returns the target.
    pub fn check_rel(&self, device: &str, from_um: f64, delta_um: f64) -> Result<f64, HwError> {
        let target_um = from_um + delta_um;
        if !delta_um.is_finite() {
            return Err(HwError::Limit {
                device: device.to_string(),
                target_um,
                reason: "the step is not a finite number".into(),
            });
        }
        self.check_move(device, from_um, target_um)?;
        Ok(target_um)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lim() -> TravelLimits {
        TravelLimits::new(0.0, 10_000.0, 500.0).unwrap()
    }

    #[test]
    fn targets_inside_pass_and_outside_are_refused() {
        assert!(lim().check_abs("axis", 0.0).is_ok());
        assert!(lim().check_abs("axis", 10_000.0).is_ok());
        let e = lim().check_abs("axis", 10_000.5).unwrap_err();
        assert!(e.to_string().contains("soft travel limits"), "{e}");
        assert!(matches!(
            lim().check_abs("axis", -1.0),
            Err(HwError::Limit { .. })
        ));
        assert!(matches!(
            lim().check_abs("axis", f64::NAN),
            Err(HwError::Limit { .. })
        ));
    }

    #[test]
    fn relative_moves_check_the_step_and_the_target() {
        assert_eq!(lim().check_rel("axis", 100.0, 50.0).unwrap(), 150.0);
        let e = lim().check_rel("axis", 100.0, 501.0).unwrap_err();
        assert!(e.to_string().contains("maximum step"), "{e}");
        assert!(lim().check_rel("axis", 9_900.0, 200.0).is_err());
        assert!(lim().check_rel("axis", 100.0, f64::INFINITY).is_err());
    }

    #[test]
    fn absolute_moves_are_steps_too() {
        assert!(lim().check_move("axis", 1000.0, 1500.0).is_ok());
        assert!(lim().check_move("axis", 1000.0, 500.0).is_ok());
        let e = lim().check_move("axis", 1000.0, 1500.5).unwrap_err();
        assert_eq!(
            e.to_string(),
            "axis: move to 1500.5 µm refused: a move of 500.5 µm from the last target 1000 µm \
             exceeds the maximum step of 500 µm"
        );
        assert!(lim().check_move("axis", f64::NAN, 1000.0).is_err());
    }

    #[test]
    fn huge_numbers_print_short() {
        let e = lim()
            .check_move("axis", 0.0, 1e308)
            .unwrap_err()
            .to_string();
        assert!(e.len() < 120 && e.contains("1e308"), "{e}");
    }

    #[test]
    fn bad_configs_are_named() {
        assert!(TravelLimits::new(5.0, 1.0, 1.0)
            .unwrap_err()
            .contains("min_um"));
        assert!(TravelLimits::new(0.0, 1.0, 0.0)
            .unwrap_err()
            .contains("max_step_um"));
        assert!(TravelLimits::new(f64::NEG_INFINITY, 1.0, 1.0).is_err());
    }
}
