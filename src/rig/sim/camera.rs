//! `Camera` over the simulated rig's frame-clock camera (`rigd_sim::FrameClockCamera`).
//!
//! Frames come from a V4L2-like ring: `grab` takes the oldest queued frame (which may have
//! been exposed before the last move ended), `grab_fresh` drops queued frames exposed before
//! `not_before` and waits for the first one exposed at or after it — the fresh-frame rule.
//! After a timeout the stream is restarted on the next grab, as the V4L2 driver does.

use crate::hw::devices::{Camera, Frame, HwError};
use rigd_sim::camera_clock::{ClockError, FrameClockCamera, SimFrame};
use std::sync::Arc;
use std::time::{Duration, SystemTime};

pub struct SimCamera {
    name: String,
    cam: Arc<FrameClockCamera>,
}

impl SimCamera {
    /// Wrap a running frame-clock camera (e.g. `SimRig::camera`).
    pub fn new(cam: Arc<FrameClockCamera>) -> SimCamera {
        SimCamera {
            name: "sim-camera".into(),
            cam,
        }
    }

    pub fn clock(&self) -> &Arc<FrameClockCamera> {
        &self.cam
    }

    fn frame(&self, r: Result<SimFrame, ClockError>, waiting_for: &str) -> Result<Frame, HwError> {
        match r {
            Ok(f) => Ok(Frame {
                image: f.image,
                sequence: f.sequence,
                timestamp: f.timestamp,
            }),
            Err(ClockError::Timeout { timeout_ms }) => {
                // A stalled stream stays stalled until STREAMOFF/STREAMON.
                self.cam.restart_stream();
                Err(HwError::Timeout {
                    device: self.name.clone(),
                    timeout_ms,
                    waiting_for: waiting_for.into(),
                })
            }
            Err(ClockError::Stopped) => Err(HwError::PortGone {
                device: self.name.clone(),
                message: "the simulated camera stopped streaming".into(),
            }),
        }
    }
}

impl Camera for SimCamera {
    fn name(&self) -> &str {
        &self.name
    }

    fn size(&self) -> (u32, u32) {
        self.cam.size()
    }

    fn grab(&mut self, timeout: Duration) -> Result<Frame, HwError> {
        let r = self.cam.next_frame(timeout);
        self.frame(r, "a frame")
    }

    fn grab_fresh(&mut self, not_before: SystemTime, timeout: Duration) -> Result<Frame, HwError> {
        let r = self
            .cam
            .fresh_frame(self.cam.instant_of(not_before), timeout);
        self.frame(r, "a frame exposed after the settle")
    }
}

/// The simulated camera together with the simulated rig it watches (kept alive with it).
pub struct SimRigCamera {
    _rig: rigd_sim::SimRig,
    cam: SimCamera,
}

impl SimRigCamera {
    pub fn new(rig: rigd_sim::SimRig, cam: SimCamera) -> SimRigCamera {
        SimRigCamera { _rig: rig, cam }
    }
}

impl Camera for SimRigCamera {
    fn name(&self) -> &str {
        self.cam.name()
    }
    fn size(&self) -> (u32, u32) {
        self.cam.size()
    }
    fn grab(&mut self, timeout: Duration) -> Result<Frame, HwError> {
        self.cam.grab(timeout)
    }
    fn grab_fresh(&mut self, not_before: SystemTime, timeout: Duration) -> Result<Frame, HwError> {
        self.cam.grab_fresh(not_before, timeout)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigd_sim::camera::CameraModel;
    use rigd_sim::{Board, FrameRenderer, SimRig, SimRigConfig};

    fn tiny() -> CameraModel {
        CameraModel {
            width: 96,
            height: 64,
            frame_period_ms: 10.0,
            exposure_ms: 4.0,
            ..Default::default()
        }
    }

    #[test]
    fn grab_fresh_skips_frames_exposed_before_not_before() {
        let rig = SimRig::start(SimRigConfig {
            camera: tiny(),
            ..Default::default()
        })
        .unwrap();
        let mut cam = SimCamera::new(rig.camera.clone());
        assert_eq!(cam.size(), (96, 64));
        std::thread::sleep(Duration::from_millis(60));
        let stale = cam.grab(Duration::from_secs(2)).unwrap();
        let now = SystemTime::now();
        let fresh = cam.grab_fresh(now, Duration::from_secs(2)).unwrap();
        assert!(stale.timestamp < now, "the queued frame predates now");
        assert!(fresh.timestamp >= now);
        assert!(
            fresh.sequence > stale.sequence + 1,
            "queued frames were dropped"
        );
        let next = cam.grab(Duration::from_secs(2)).unwrap();
        assert_eq!(next.sequence, fresh.sequence + 1);
    }

    #[test]
    fn a_stopped_camera_is_an_error_naming_it() {
        let r = FrameRenderer::new(Board::paper(), tiny(), 1).unwrap();
        let axis: Arc<dyn rigd_sim::motion::TruePosition> = Arc::new(rigd_sim::motion::Axis::new(
            rigd_sim::motion::AxisParams::default(),
        ));
        let clock = Arc::new(FrameClockCamera::start(r, axis));
        let mut cam = SimCamera::new(clock.clone());
        clock.stop();
        let e = cam.grab(Duration::from_millis(20)).unwrap_err();
        assert!(matches!(e, HwError::PortGone { .. }), "{e}");
        assert!(e.to_string().contains("sim-camera"));
    }
}
