//! Hardware drivers: the GRBL axis and the PI GCS piezo over serial, V4L2 cameras (feature
//! `v4l2`), their option structs, pixel formats and soft travel limits. Each driver
//! implements a device trait of [`crate::hw::devices`], re-exported here; the drivers know
//! nothing of the config file or the daemon (the rig builders turn config into their
//! options).

pub mod devices;
pub mod gcs;
pub mod grbl;
pub mod grbl_codes;
mod grbl_lines;
pub mod limits;
pub mod pixfmt;
pub mod poll_budget;
pub mod serial;
pub mod stage_machine;
#[cfg(feature = "v4l2")]
pub mod v4l2;
pub mod v4l2_options;

pub use devices::{
    Camera, Frame, HwError, LogSample, LogSource, MotionState, PositionLog, Stage, StageMachine,
    StageStatus,
};
pub use image::RgbImage;
