//! The rig a job runs on: stages, camera, interferometer, and what the daemon knows about them
//! up front (limits, scale, frame size) to check a job before anything moves.
//!
//! The runner owns a `Rig` for the length of one job, on its own blocking thread.

use crate::acquisition::Processing;
use crate::acquisition::StageKind;
use crate::hw::{Camera, HwError, Stage};
use rigd_sim::Board;
use serde::{Deserialize, Serialize};
use std::time::SystemTime;

/// Where the interferometer says the stage is: the XL-80's live log, followed as it grows
/// (`daemon::interferometer::FollowedLog`, on the sim rig and on hardware alike), or a
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

/// Static facts about a rig, known before a job starts.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RigInfo {
    /// "sim", "replay" or "hardware".
    pub mode: String,
    /// Soft travel limits of the axis and the piezo (None: no piezo).
    pub axis_limits_um: [f64; 2],
    pub piezo_limits_um: Option<[f64; 2]>,
    /// Where a scan starts when the job gives no `start_um`.
    pub default_start_um: f64,
    pub scale_um_per_px: f64,
    /// Image displacement per unit of axis travel (the camera rides the axis).
    pub axis_dir: [f64; 2],
    pub frame_size: (u32, u32),
    /// Whether the rig has an interferometer log (`registration: interferometer` needs one).
    #[serde(default)]
    pub interferometer: bool,
    /// The board the camera looks at, to name targets.
    pub board: Option<Board>,
    /// A snapshot of the configuration this rig was built from (recorded in sessions).
    pub config: serde_json::Value,
    /// `[pipeline]` defaults for what a job leaves out (none on `rigd --sim`: the
    /// protocol's own apply).
    #[serde(default)]
    pub job_defaults: Processing,
    /// How long a grab may wait for a fresh frame ([camera] frame_timeout_ms).
    #[serde(default = "default_grab_timeout_ms")]
    pub grab_timeout_ms: u64,
}

/// The grab deadline when nothing configures one (and of sessions recorded before it was).
pub const DEFAULT_GRAB_TIMEOUT_MS: u64 = 5000;

fn default_grab_timeout_ms() -> u64 {
    DEFAULT_GRAB_TIMEOUT_MS
}

impl RigInfo {
    pub fn limits_um(&self, stage: StageKind) -> Option<[f64; 2]> {
        match stage {
            StageKind::Axis => Some(self.axis_limits_um),
            StageKind::Piezo => self.piezo_limits_um,
        }
    }
}

/// The hardware one job uses, moved into the job's blocking thread and back.
pub struct Rig {
    pub info: RigInfo,
    pub axis: Box<dyn Stage>,
    pub piezo: Option<Box<dyn Stage>>,
    pub camera: Box<dyn Camera>,
    pub log: Option<Box<dyn PositionLog>>,
}

impl Rig {
    pub fn stage(&mut self, kind: StageKind) -> Result<&mut dyn Stage, HwError> {
        match kind {
            StageKind::Axis => Ok(self.axis.as_mut()),
            StageKind::Piezo => match self.piezo.as_mut() {
                Some(p) => Ok(p.as_mut()),
                None => Err(HwError::Other {
                    device: "piezo".into(),
                    message: "this rig has no piezo".into(),
                }),
            },
        }
    }
}
