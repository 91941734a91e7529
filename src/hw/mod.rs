//! Hardware as small blocking traits, in the style of embedded-hal: the job runner is generic
//! over them, each has a driver for the real part and an implementation backed by the
//! simulated rig. Positions are micrometres everywhere.
//!
//! The traits are synchronous on purpose: serial and V4L2 I/O are blocking calls with
//! deadlines, and the daemon runs them on a dedicated blocking thread per job.

pub mod gcs;
pub mod grbl;
pub mod grbl_codes;
pub mod limits;
pub mod open;
pub mod pixfmt;
pub mod serial;
pub mod sim_camera;
pub mod sim_stage;
pub mod stage_config;
#[cfg(feature = "v4l2")]
pub mod v4l2;

use std::time::{Duration, SystemTime};

pub use image::RgbImage;

/// What went wrong talking to a device. Every variant names the device it came from.
#[derive(Debug, thiserror::Error)]
pub enum HwError {
    #[error("{device}: no reply within {timeout_ms} ms (waiting for {waiting_for})")]
    Timeout {
        device: String,
        timeout_ms: u64,
        waiting_for: String,
    },
    #[error("{device}: port gone: {message}")]
    PortGone { device: String, message: String },
    #[error("{device}: alarm {code}: {message}")]
    Alarm {
        device: String,
        code: u32,
        message: String,
    },
    #[error("{device}: error {code}: {message}")]
    Controller {
        device: String,
        code: i32,
        message: String,
    },
    #[error("{device}: unexpected reply {reply:?} (waiting for {waiting_for})")]
    Protocol {
        device: String,
        reply: String,
        waiting_for: String,
    },
    #[error("{device}: move to {target_um} µm refused: {reason}")]
    Limit {
        device: String,
        target_um: f64,
        reason: String,
    },
    #[error("{device}: {message}")]
    Other { device: String, message: String },
}

/// Motion state as the controller reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MotionState {
    Idle,
    Moving,
    Holding,
    Homing,
    Alarm,
}

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StageStatus {
    pub state: MotionState,
    pub position_um: f64,
}

/// A single linear axis: the numerically controlled axis or the piezo flexure.
pub trait Stage: Send {
    /// Short name for messages ("axis", "piezo").
    fn name(&self) -> &str;
    /// Start a relative move; returns once the controller accepted it.
    fn move_rel(&mut self, delta_um: f64) -> Result<(), HwError>;
    /// Start an absolute move.
    fn move_abs(&mut self, target_um: f64) -> Result<(), HwError>;
    /// Block until motion has finished and the axis is settled; returns the reported position.
    fn wait_settled(&mut self, timeout: Duration) -> Result<f64, HwError>;
    /// Reported position.
    fn position_um(&mut self) -> Result<f64, HwError>;
    /// Stop now (feed hold / halt), leaving the axis stopped and usable.
    fn stop(&mut self) -> Result<(), HwError>;
    /// Run the homing cycle.
    fn home(&mut self) -> Result<(), HwError>;
    fn status(&mut self) -> Result<StageStatus, HwError>;
}

/// One captured frame.
#[derive(Debug, Clone)]
pub struct Frame {
    pub image: RgbImage,
    /// Driver sequence number (increasing; gaps mean dropped frames).
    pub sequence: u64,
    /// When the exposure happened (the driver's timestamp, on the system clock).
    pub timestamp: SystemTime,
}

/// A camera that yields RGB frames.
pub trait Camera: Send {
    fn name(&self) -> &str;
    /// Frame size in pixels.
    fn size(&self) -> (u32, u32);
    /// The next frame, whatever its age.
    fn grab(&mut self, timeout: Duration) -> Result<Frame, HwError>;
    /// The first frame exposed at or after `not_before`: queued older frames are dropped.
    /// This is the fresh-frame rule after a move has settled.
    fn grab_fresh(&mut self, not_before: SystemTime, timeout: Duration) -> Result<Frame, HwError>;
}
