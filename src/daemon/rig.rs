//! The rig a job runs on: stages, camera, interferometer, and what the daemon knows about them
//! up front (limits, scale, frame size) to check a job before anything moves.
//!
//! The runner owns a `Rig` for the length of one job, on its own blocking thread.

use crate::config::JobDefaults;
use crate::daemon::protocol::StageKind;
use crate::hw::{Camera, HwError, Stage};
use rigd_sim::Board;
use serde::{Deserialize, Serialize};
use std::time::SystemTime;

/// Where the interferometer says the stage is. The sim reads the axis' true position; a real
/// rig follows the XL-80's live log.
pub trait PositionLog: Send {
    /// The reading closest to `t`, if the log covers it.
    fn position_at(&mut self, t: SystemTime) -> Option<f64>;
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
    /// The board the camera looks at, to name targets.
    pub board: Option<Board>,
    /// A snapshot of the configuration this rig was built from (recorded in sessions).
    pub config: serde_json::Value,
    /// `[pipeline]` defaults for what a job leaves out (none on `rigd --sim`: the
    /// protocol's own apply).
    #[serde(default)]
    pub job_defaults: JobDefaults,
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
