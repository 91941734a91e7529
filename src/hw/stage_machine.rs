//! What a stage's controller says of its own motion: the motor's step, its top speed and
//! acceleration (GRBL's `$100`, `$110`, `$120`), in µm. From them follow the step the
//! axis really makes for a commanded one, and how long a move takes at the controller's
//! own rate — what the engine's deadlines scale with.

use serde::{Deserialize, Serialize};
use std::time::Duration;

/// How finely a status report gives positions, µm (GRBL prints mm to 3 decimals).
pub const REPORT_RESOLUTION_UM: f64 = 1.0;

/// A stage controller's own motion settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct StageMachine {
    /// The controller ("grbl").
    pub controller: String,
    /// One motor step, µm (GRBL: 1000 / `$100`).
    pub motor_step_um: f64,
    /// The fastest the controller moves the axis, µm/s (GRBL: `$110` mm/min).
    pub max_rate_um_s: f64,
    /// Its acceleration, µm/s² (GRBL: `$120` mm/s²).
    pub accel_um_s2: f64,
}

impl StageMachine {
    /// `step_um` in motor steps.
    pub fn steps(&self, step_um: f64) -> f64 {
        step_um / self.motor_step_um
    }

    /// Whether `step_um` is a whole number of motor steps (to 0.1 % of one).
    pub fn is_whole(&self, step_um: f64) -> bool {
        let s = self.steps(step_um);
        (s - s.round()).abs() < 1e-3
    }

    /// A step that is not whole, as the axis makes it: the two whole-step moves it takes
    /// turn about (`(lower, upper)`, µm), or None when the step is whole.
    pub fn uneven_step_um(&self, step_um: f64) -> Option<(f64, f64)> {
        if self.is_whole(step_um) {
            return None;
        }
        let s = self.steps(step_um.abs());
        Some((
            s.floor() * self.motor_step_um,
            s.ceil() * self.motor_step_um,
        ))
    }

    /// Where the axis stands after a move to `commanded_um` that the controller reports at
    /// `reported_um`: the reported position snapped to whole motor steps, when the two differ
    /// by at most one step and a step is coarse enough for the report to tell steps apart;
    /// else `commanded_um` (a finer step is below what a report resolves).
    pub fn reached_um(&self, commanded_um: f64, reported_um: f64) -> f64 {
        let step = self.motor_step_um;
        let coarse = step >= 2.0 * REPORT_RESOLUTION_UM;
        if !coarse || !reported_um.is_finite() || (reported_um - commanded_um).abs() > step {
            return commanded_um;
        }
        (reported_um / step).round() * step
    }

    /// How long a move of `distance_um` from rest to rest takes at `feed_um_s` (capped at
    /// the controller's top speed), accelerating and braking at its acceleration.
    pub fn move_time(&self, distance_um: f64, feed_um_s: f64) -> Duration {
        let d = distance_um.abs();
        let v = feed_um_s.min(self.max_rate_um_s);
        let a = self.accel_um_s2;
        if !(d.is_finite() && v > 0.0 && a > 0.0) {
            return Duration::ZERO;
        }
        let secs = if d < v * v / a {
            2.0 * (d / a).sqrt() // never reaches the feed: a triangle
        } else {
            d / v + v / a
        };
        Duration::try_from_secs_f64(secs).unwrap_or(Duration::MAX)
    }

    /// How long the axis takes to brake from `feed_um_s` (capped at the top speed) to rest.
    pub fn brake_time(&self, feed_um_s: f64) -> Duration {
        let v = feed_um_s.min(self.max_rate_um_s);
        Duration::try_from_secs_f64(v / self.accel_um_s2).unwrap_or(Duration::MAX)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// GRBL 1.1h's defaults: `$100=250`, `$110=500`, `$120=10`.
    fn grbl_defaults() -> StageMachine {
        StageMachine {
            controller: "grbl".into(),
            motor_step_um: 4.0,
            max_rate_um_s: 500.0 * 1000.0 / 60.0,
            accel_um_s2: 10_000.0,
        }
    }

    #[test]
    fn a_step_between_motor_steps_is_named_as_the_two_the_axis_makes() {
        let m = grbl_defaults();
        assert_eq!(m.uneven_step_um(50.0), Some((48.0, 52.0)));
        assert_eq!(m.uneven_step_um(100.0), None);
        assert_eq!(m.uneven_step_um(-50.0), Some((48.0, 52.0)));
        assert!(m.is_whole(4.0) && !m.is_whole(2.0));
    }

    #[test]
    fn the_reached_position_is_the_report_in_whole_steps_when_a_step_is_coarse() {
        let m = grbl_defaults();
        assert_eq!(m.reached_um(1050.0, 1052.0), 1052.0);
        assert_eq!(m.reached_um(1050.0, 1048.0), 1048.0);
        // Off by more than a step: not quantisation, so the commanded position stands.
        assert_eq!(m.reached_um(1050.0, 1060.0), 1050.0);
        let fine = StageMachine {
            motor_step_um: 0.625,
            ..m
        };
        assert_eq!(fine.reached_um(1050.3, 1050.0), 1050.3);
    }

    #[test]
    fn move_times_follow_the_trapezoid_at_the_capped_rate() {
        let m = grbl_defaults();
        // 50 µm at 10 mm²/s² never cruises: 2·sqrt(d/a) = 0.1414 s.
        let t = m.move_time(50.0, 10_000.0).as_secs_f64();
        assert!((t - 0.14142).abs() < 1e-4, "{t}");
        // 20 mm at 10 mm/s, capped to 8.33 mm/s: 2.4 s cruising + 0.833 s of ramps.
        let t = m.move_time(20_000.0, 10_000.0).as_secs_f64();
        assert!((t - (2.4 + 0.8333)).abs() < 1e-3, "{t}");
        assert!((m.brake_time(10_000.0).as_secs_f64() - 0.8333).abs() < 1e-3);
    }
}
