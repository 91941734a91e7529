//! Soft travel limits and a maximum step, checked before any motion command is sent.
//!
//! They guard against a wrong unit or a bad job (50 mm typed for 50 µm) independently of the
//! controller's own limits: the drivers refuse the move with [`HwError::Limit`] and nothing
//! moves. The maximum step applies to relative moves (a scan's steps); absolute moves, such
//! as going to a scan's start, are bounded by the travel limits alone.

use super::HwError;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TravelLimits {
    /// Lowest allowed target, µm.
    pub min_um: f64,
    /// Highest allowed target, µm.
    pub max_um: f64,
    /// Largest allowed relative move, µm.
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
            return Err(format!("travel limits must be finite numbers: {self:?}"));
        }
        if self.min_um >= self.max_um {
            return Err(format!(
                "min_um ({}) must be below max_um ({})",
                self.min_um, self.max_um
            ));
        }
        if self.max_step_um <= 0.0 {
            return Err(format!(
                "max_step_um must be positive, not {}",
                self.max_step_um
            ));
        }
        Ok(())
    }

    /// An absolute target inside the travel.
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
                self.min_um, self.max_um
            )));
        }
        Ok(())
    }

    /// A relative move from `from_um`: the step size and the target; returns the target.
    pub fn check_rel(&self, device: &str, from_um: f64, delta_um: f64) -> Result<f64, HwError> {
        let target_um = from_um + delta_um;
        if !delta_um.is_finite() {
            return Err(HwError::Limit {
                device: device.to_string(),
                target_um,
                reason: "the step is not a finite number".into(),
            });
        }
        if delta_um.abs() > self.max_step_um {
            return Err(HwError::Limit {
                device: device.to_string(),
                target_um,
                reason: format!(
                    "step of {delta_um} µm exceeds the maximum step of {} µm",
                    self.max_step_um
                ),
            });
        }
        self.check_abs(device, target_um)?;
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
