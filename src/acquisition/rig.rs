//! The rig as a job sees it: [`RigInfo`], what is known of it before anything moves
//! (limits, scale, frame size, its machine) to check a job at submit, and [`Rig`], the
//! devices one job uses. The builders that make them from a config, the simulator or a
//! recorded session are in `crate::rig`.

use super::{Processing, StageKind};
use crate::board::Board;
use crate::hw::{Camera, HwError, PositionLog, Stage};
use serde::{Deserialize, Serialize};

/// Which kind of rig a daemon runs (recorded in sessions as "sim", "replay", "hardware").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum RigMode {
    /// The simulated rig (`rigd --sim`, or a config whose every driver is "sim").
    Sim,
    /// A recorded session played back.
    Replay,
    /// Real devices from a config.
    Hardware,
}

impl std::fmt::Display for RigMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            RigMode::Sim => "sim",
            RigMode::Replay => "replay",
            RigMode::Hardware => "hardware",
        })
    }
}

/// What a job's moves on one stage must respect, for a plan to check at submit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StageBounds {
    /// Soft travel limits, µm.
    pub limits_um: [f64; 2],
    /// Largest relative move the driver accepts, µm (`None`: unlimited).
    pub max_step_um: Option<f64>,
    /// The stage's own settle after a move (`[axis] settle_ms`), ms (`None`: none configured).
    pub settle_ms: Option<u64>,
}

/// Static facts about a rig, known before a job starts.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RigInfo {
    pub mode: RigMode,
    /// Soft travel limits of the axis and the piezo (None: no piezo).
    pub axis_limits_um: [f64; 2],
    pub piezo_limits_um: Option<[f64; 2]>,
    /// Largest relative move of each stage, µm (`[axis]`/`[piezo] max_step_um`; None:
    /// unlimited, and in sessions recorded before it was kept).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_max_step_um: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub piezo_max_step_um: Option<f64>,
    /// Each stage's own settle after a move, ms (`[axis]`/`[piezo] settle_ms`; None: none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_settle_ms: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub piezo_settle_ms: Option<u64>,
    /// Where a scan starts when the job gives no `start_um`.
    pub default_start_um: f64,
    pub scale_um_per_px: f64,
    /// Image displacement per unit of axis travel (the camera rides the axis).
    pub axis_dir: [f64; 2],
    /// Image displacement per unit of piezo travel (`[pipeline] piezo_dir`; None: the
    /// axis's, as in sessions recorded before it was kept).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub piezo_dir: Option<[f64; 2]>,
    pub frame_size: (u32, u32),
    /// The camera's output curve (`[camera] response`): frames are measured in linear light.
    /// Sessions recorded before it was kept were measured as linear.
    #[serde(default)]
    pub response: crate::pipeline::Response,
    /// The print's ink density statistics (`[camera] ink_prior`), when known: the fit then
    /// takes the print's uneven density as a prior.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ink_prior: Option<crate::pipeline::InkPrior>,
    /// Whether the rig has an interferometer log (`registration: interferometer` needs one).
    #[serde(default)]
    pub interferometer: bool,
    /// The axis controller's own motion settings (GRBL's `$100`/`$110`/`$120`), when it
    /// tells them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_machine: Option<crate::hw::devices::StageMachine>,
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

    /// Image displacement per unit of `stage`'s travel.
    pub fn dir(&self, stage: StageKind) -> [f64; 2] {
        match stage {
            StageKind::Axis => self.axis_dir,
            StageKind::Piezo => self.piezo_dir.unwrap_or(self.axis_dir),
        }
    }

    /// Everything a job's moves on `stage` must respect (None: the rig has no such stage).
    pub fn bounds(&self, stage: StageKind) -> Option<StageBounds> {
        let (max_step_um, settle_ms) = match stage {
            StageKind::Axis => (self.axis_max_step_um, self.axis_settle_ms),
            StageKind::Piezo => (self.piezo_max_step_um, self.piezo_settle_ms),
        };
        Some(StageBounds {
            limits_um: self.limits_um(stage)?,
            max_step_um,
            settle_ms,
        })
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A `rig` as sessions recorded it before the mode was an enum and the step and settle
    /// bounds were kept.
    const OLD_MANIFEST_RIG: &str = r#"{
        "mode": "replay", "axis_limits_um": [0.0, 250000.0], "piezo_limits_um": [0.0, 1400.0],
        "default_start_um": 1000.0, "scale_um_per_px": 774.0, "axis_dir": [-1.0, 0.0],
        "frame_size": [64, 48], "board": null, "config": null
    }"#;

    #[test]
    fn old_manifests_read_and_the_mode_keeps_its_strings() {
        let info: RigInfo = serde_json::from_str(OLD_MANIFEST_RIG).unwrap();
        assert_eq!(info.mode, RigMode::Replay);
        assert_eq!(info.axis_max_step_um, None);
        assert_eq!(info.grab_timeout_ms, DEFAULT_GRAB_TIMEOUT_MS);
        for (mode, s) in [
            (RigMode::Sim, "sim"),
            (RigMode::Replay, "replay"),
            (RigMode::Hardware, "hardware"),
        ] {
            assert_eq!(serde_json::to_value(mode).unwrap(), s);
            assert_eq!(mode.to_string(), s);
        }
        let json = serde_json::to_value(&info).unwrap();
        assert!(json.get("axis_max_step_um").is_none(), "{json}");
    }

    #[test]
    fn bounds_are_per_stage_and_none_without_the_stage() {
        let mut info: RigInfo = serde_json::from_str(OLD_MANIFEST_RIG).unwrap();
        info.piezo_max_step_um = Some(20.0);
        info.piezo_settle_ms = Some(15);
        assert_eq!(
            info.bounds(StageKind::Piezo),
            Some(StageBounds {
                limits_um: [0.0, 1400.0],
                max_step_um: Some(20.0),
                settle_ms: Some(15),
            })
        );
        assert_eq!(info.bounds(StageKind::Axis).unwrap().max_step_um, None);
        info.piezo_limits_um = None;
        assert_eq!(info.bounds(StageKind::Piezo), None);
    }
}
