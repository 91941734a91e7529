//! The three devices a job drives, as small blocking traits in the style of embedded-hal:
//! a [`Stage`] (the axis, the piezo), a [`Camera`] and a [`PositionLog`] (the
//! interferometer). Positions are micrometres everywhere.
//!
//! The traits are synchronous on purpose: serial and V4L2 I/O are blocking calls with
//! deadlines, and the daemon runs them on a dedicated blocking thread per job. This module
//! depends on nothing else in rigd but [`StageMachine`] (what a controller says of its own
//! motion): the drivers in `hw` implement it (and re-export it), the rig builders assemble it.

pub use super::stage_machine::StageMachine;
use crate::text::short_um;
use image::RgbImage;
use serde::{Deserialize, Serialize};
use std::time::{Duration, SystemTime};

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
    /// The controller answered every poll, but the motion did not end in time.
    #[error("{device}: not settled within {timeout_ms} ms (the controller answered every poll: {state})")]
    NotSettled {
        device: String,
        timeout_ms: u64,
        state: String,
    },
    #[error("{device}: move to {} µm refused: {reason}", short_um(*target_um))]
    Limit {
        device: String,
        target_um: f64,
        reason: String,
    },
    #[error("{device}: {message}")]
    Other { device: String, message: String },
}

/// Motion state as the controller reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum MotionState {
    Idle,
    Moving,
    Holding,
    Homing,
    Alarm,
}

impl std::fmt::Display for MotionState {
    /// Its wire name (`idle`, `moving`, ...), as messages show it.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            MotionState::Idle => "idle",
            MotionState::Moving => "moving",
            MotionState::Holding => "holding",
            MotionState::Homing => "homing",
            MotionState::Alarm => "alarm",
        })
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
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
    /// Run the homing cycle (or the driver's configured home move) and wait for it.
    fn home(&mut self) -> Result<(), HwError>;
    /// [`Stage::home`], abandoned as soon as `stopped()` says so (polled while it runs):
    /// `Ok(true)` when it was stopped, the stage halted the controller's way (GRBL: a soft
    /// reset, which leaves it in alarm). A driver that cannot stop its homing runs it whole.
    fn home_stoppable(&mut self, stopped: &dyn Fn() -> bool) -> Result<bool, HwError> {
        let _ = stopped;
        self.home().map(|()| false)
    }
    fn status(&mut self) -> Result<StageStatus, HwError>;
    /// Clear a latched alarm or error the controller's own way (GRBL `$X`; GCS `ERR?`, servo
    /// on again). `Ok` only once the controller confirms it is usable.
    fn unlock(&mut self) -> Result<(), HwError> {
        Err(unsupported(self.name(), "unlock"))
    }
    /// Resume after a feed hold (GRBL cycle start `~`): the controller goes on with what
    /// it held. `Ok` when nothing was held.
    fn resume(&mut self) -> Result<(), HwError> {
        Err(unsupported(self.name(), "resume after a hold"))
    }
    /// Close the port and open it again, handshake included (after the port was lost).
    fn reconnect(&mut self) -> Result<(), HwError> {
        Err(unsupported(self.name(), "reconnect"))
    }
    /// The controller's own motion settings (motor step, top speed, acceleration), when it
    /// tells them: None for a stage that does not.
    fn machine(&self) -> Option<StageMachine> {
        None
    }
    /// How long the last move sent takes at the controller's own rate and acceleration, when
    /// the driver knows: the engine's move deadline grows by it.
    fn planned_move(&self) -> Option<Duration> {
        None
    }
}

/// `f`'s result, or, if it panics, an error of `device` naming the panic: a driver's panic
/// fails the request it served, never the thread that owns the rig.
pub fn panic_free<T>(device: &str, f: impl FnOnce() -> Result<T, HwError>) -> Result<T, HwError> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(p) => {
            let message = crate::text::panic_message(p.as_ref());
            tracing::error!(device, panic = %message, "a device call panicked");
            Err(HwError::Other {
                device: device.to_string(),
                message: format!("internal error: panicked: {message}"),
            })
        }
    }
}

fn unsupported(device: &str, what: &str) -> HwError {
    HwError::Other {
        device: device.to_string(),
        message: format!("this driver cannot {what}"),
    }
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

/// Where the interferometer says the stage is: the XL-80's live log, followed as it grows
/// (`rig::FollowedLog`, on the sim rig and on hardware alike), or a
/// recorded session's log on replay.
pub trait PositionLog: Send {
    /// A job starts at `from`: catch up with the log and hand on only samples from then on.
    fn begin(&mut self, from: SystemTime);
    /// The reading at `t` (µm, the laser's own datum and sign), waiting briefly for the log
    /// to reach `t`; `None` if it does not cover `t`.
    fn position_at(&mut self, t: SystemTime) -> Option<f64>;
    /// Samples read since the last call (since `begin` at first), oldest first, for the
    /// session's `interferometer.csv`.
    fn take_samples(&mut self) -> Vec<LogSample>;
    /// What the source log says about itself, for the session's manifest.
    fn source(&self) -> LogSource;
    /// The job ended. A log written for the job (the simulated laser's) stops growing; a
    /// real log, written by the laser's own software, is only followed and left alone.
    fn end(&mut self) {}
    /// One reading now, outside a job (`position`), without waiting: the newest sample of a
    /// log that is being written, or a single reading taken on request; `Err` says why
    /// there is none.
    fn reading_now(&mut self) -> Result<LogSample, String> {
        Err("this interferometer gives readings only during jobs".into())
    }
}

/// One interferometer sample on the PC clock.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LogSample {
    pub t_unix_s: f64,
    /// The laser's reading, µm (its own datum and sign).
    pub position_um: f64,
    /// Line (CSV) or sample number (RTX) in the source log.
    pub sample: usize,
}

/// The source log's facts, recorded in the manifest (`interferometer`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LogSource {
    /// The log file followed.
    pub path: String,
    /// "csv" or "rtx".
    pub format: String,
    /// µm per unit of the file's positions (its header's unit, else the assumed one).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub um_per_unit: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sample_rate_hz: Option<f64>,
    /// The log's start date as written (whole seconds in both formats).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub date: Option<String>,
    /// Log clock minus PC clock, seconds, subtracted from every sample time.
    pub log_minus_pc_s: f64,
    /// Where `log_minus_pc_s` comes from.
    #[serde(default)]
    pub clock: String,
    /// Every header `key: value` pair, in file order.
    #[serde(default)]
    pub fields: Vec<(String, String)>,
    /// Garbled lines/samples seen in the source so far.
    #[serde(default)]
    pub garbled: usize,
    /// Set on replay: the session whose recorded log this is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub replayed_from: Option<String>,
}
