//! An in-process [`Stage`] over a simulated axis: no pty, no protocol, for fast tests of job
//! logic. The motion is the same `Axis` the emulators drive (finite speed, positioning error,
//! hard limits), so a camera or interferometer watching it sees the same thing.

use crate::hw::devices::{HwError, MotionState, Stage, StageStatus};
use crate::hw::limits::TravelLimits;
use rigd_sim::motion::{Axis, MotionError};
use std::sync::Arc;
use std::time::{Duration, Instant};

pub struct SimStage {
    name: String,
    axis: Arc<Axis>,
    limits: TravelLimits,
    /// Where the last accepted move ends (the controller's idea).
    target_um: f64,
    /// Tripped a hard limit: moves refused until `home()`.
    alarm: bool,
    /// Machine position the homing cycle goes to.
    home_um: f64,
}

impl SimStage {
    pub fn new(name: impl Into<String>, axis: Arc<Axis>, limits: TravelLimits) -> SimStage {
        let target_um = axis.reported_um(Instant::now());
        SimStage {
            name: name.into(),
            axis,
            limits,
            target_um,
            alarm: false,
            home_um: 0.0,
        }
    }

    pub fn axis(&self) -> &Arc<Axis> {
        &self.axis
    }

    fn start(&mut self, target_um: f64) -> Result<(), HwError> {
        if self.alarm {
            return Err(HwError::Alarm {
                device: self.name.clone(),
                code: 1,
                message: "hard limit tripped earlier: home to clear".into(),
            });
        }
        match self.axis.command_move(target_um) {
            Ok(_) => {
                self.target_um = target_um;
                Ok(())
            }
            Err(MotionError::HardLimit { min_um, max_um, .. }) => {
                self.alarm = true;
                Err(HwError::Alarm {
                    device: self.name.clone(),
                    code: 1,
                    message: format!("hard limit: travel is [{min_um}, {max_um}] µm"),
                })
            }
        }
    }
}

impl Stage for SimStage {
    fn name(&self) -> &str {
        &self.name
    }

    fn move_rel(&mut self, delta_um: f64) -> Result<(), HwError> {
        let target = self
            .limits
            .check_rel(&self.name, self.target_um, delta_um)?;
        self.start(target)
    }

    fn move_abs(&mut self, target_um: f64) -> Result<(), HwError> {
        self.limits
            .check_move(&self.name, self.target_um, target_um)?;
        self.start(target_um)
    }

    fn wait_settled(&mut self, timeout: Duration) -> Result<f64, HwError> {
        let ends = self.axis.move_ends_at();
        let now = Instant::now();
        if ends > now + timeout {
            std::thread::sleep(timeout);
            return Err(HwError::Timeout {
                device: self.name.clone(),
                timeout_ms: timeout.as_millis() as u64,
                waiting_for: "the end of the move".into(),
            });
        }
        std::thread::sleep(ends.saturating_duration_since(now));
        Ok(self.axis.reported_um(Instant::now()))
    }

    fn position_um(&mut self) -> Result<f64, HwError> {
        Ok(self.axis.reported_um(Instant::now()))
    }

    fn stop(&mut self) -> Result<(), HwError> {
        self.axis.stop();
        self.target_um = self.axis.reported_um(Instant::now());
        Ok(())
    }

    fn home(&mut self) -> Result<(), HwError> {
        self.alarm = false;
        let d = self
            .axis
            .command_move(self.home_um)
            .map_err(|e| HwError::Other {
                device: self.name.clone(),
                message: e.to_string(),
            })?;
        std::thread::sleep(d);
        self.axis.set_position(self.home_um);
        self.target_um = self.home_um;
        Ok(())
    }

    /// Like GRBL's `$X`: the alarm is cleared, the position kept.
    fn unlock(&mut self) -> Result<(), HwError> {
        self.alarm = false;
        self.target_um = self.axis.reported_um(Instant::now());
        Ok(())
    }

    fn status(&mut self) -> Result<StageStatus, HwError> {
        let now = Instant::now();
        let state = if self.alarm {
            MotionState::Alarm
        } else if self.axis.is_moving(now) {
            MotionState::Moving
        } else {
            MotionState::Idle
        };
        Ok(StageStatus {
            state,
            position_um: self.axis.reported_um(now),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigd_sim::motion::AxisParams;

    fn stage() -> SimStage {
        let axis = Arc::new(Axis::new(AxisParams::default()));
        SimStage::new(
            "axis",
            axis,
            TravelLimits::new(0.0, 10_000.0, 1_000.0).unwrap(),
        )
    }

    #[test]
    fn moves_settle_near_the_target_and_limits_refuse_before_motion() {
        let mut s = stage();
        s.move_rel(50.0).unwrap();
        assert_eq!(s.status().unwrap().state, MotionState::Moving);
        let p = s.wait_settled(Duration::from_secs(1)).unwrap();
        assert_eq!(p, 50.0);
        let truth = s.axis().position_at(Instant::now());
        assert!((truth - 50.0).abs() < 10.0, "true position {truth}");
        s.move_abs(500.0).unwrap();
        assert_eq!(s.wait_settled(Duration::from_secs(1)).unwrap(), 500.0);
        assert!(matches!(s.move_rel(1_001.0), Err(HwError::Limit { .. })));
        assert!(matches!(s.move_abs(-1.0), Err(HwError::Limit { .. })));
        assert!(!s.axis().is_moving(Instant::now()));
        assert_eq!(s.position_um().unwrap(), 500.0);
    }

    #[test]
    fn stop_halts_mid_move() {
        let axis = Arc::new(Axis::new(AxisParams::default()));
        let lim = TravelLimits::new(0.0, 10_000.0, 5_000.0).unwrap();
        let mut s = SimStage::new("axis", axis, lim);
        s.move_abs(5_000.0).unwrap();
        std::thread::sleep(Duration::from_millis(30));
        s.stop().unwrap();
        let p = s.position_um().unwrap();
        assert!(p > 0.0 && p < 5_000.0, "{p}");
        assert_eq!(s.status().unwrap().state, MotionState::Idle);
    }
}
