//! The rig a job runs on: its devices (two stages, a camera, an interferometer log) and what
//! the daemon knows about them up front ([`RigInfo`]: limits, scale, frame size) to check a
//! job before anything moves. The runner owns a [`Rig`] for the length of one job, on its own
//! blocking thread.
//!
//! - [`devices`]: the device traits [`Stage`], [`Camera`], [`PositionLog`] (a leaf: the
//!   drivers in `hw` implement them);
//! - three builders, each making the [`RigInfo`] once: [`from_config`] (`rigd --config`;
//!   also [`open_stage`]/[`open_camera`] for `rigctl hw`), [`simulated`] (`rigd --sim`,
//!   feature `sim`) and [`replay`] (a recorded session);
//! - [`FollowedLog`]: the XL-80's growing log as a [`PositionLog`], on hardware and sim alike.

pub mod followed_log;
pub mod open;
pub mod replay;
#[cfg(feature = "sim")]
pub mod sim;

pub use crate::hw::devices::{
    Camera, Frame, HwError, LogSample, LogSource, MotionState, PositionLog, Stage, StageStatus,
};
pub use followed_log::FollowedLog;
pub use open::{from_config, open_camera, open_stage};
pub use replay::replay;
#[cfg(feature = "sim")]
pub use sim::{simulated, simulated_with_truth, Fault, SimSettings, SimTruth};

pub use crate::acquisition::rig::{Rig, RigInfo, RigMode, StageBounds, DEFAULT_GRAB_TIMEOUT_MS};
