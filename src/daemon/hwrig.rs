//! The rig `rigd --config FILE` runs: built from the config's `[axis]`, `[piezo]`, `[camera]`,
//! `[board]` and `[xl80]` through `hw::open`. When every device's driver is "sim" the
//! devices are one `SimRig` (`open_sim_rig`), so the camera sees the stages move.

use crate::config::{CameraDriver, Config, StageDriver};
use crate::daemon::interferometer::FollowedLog;
use crate::daemon::rig::{PositionLog, Rig, RigInfo};
use crate::daemon::simxl80::SimXl80;
use crate::hw::open::{open_camera, open_sim_rig, open_stage, SimRigCamera};
use crate::hw::{Camera, HwError};
use crate::xl80::follow::Follower;
use crate::xl80::Xl80Format;
use std::time::Duration;

fn missing(section: &str, cfg: &Config) -> HwError {
    HwError::Other {
        device: section.trim_matches(['[', ']']).into(),
        message: format!(
            "{}: the daemon needs a {section} section",
            cfg.source.display()
        ),
    }
}

/// Build the rig a config describes, connecting to its devices now.
pub fn rig_from_config(cfg: &Config) -> Result<Rig, HwError> {
    let axis_cfg = cfg.axis.as_ref().ok_or_else(|| missing("[axis]", cfg))?;
    let cam_cfg = cfg
        .camera
        .as_ref()
        .ok_or_else(|| missing("[camera]", cfg))?;
    let all_sim = axis_cfg.driver == StageDriver::Sim
        && cfg
            .piezo
            .as_ref()
            .is_none_or(|p| p.driver == StageDriver::Sim)
        && cam_cfg.driver == CameraDriver::Sim;
    let board = match &cfg.board {
        Some(b) => Some(rigd_sim::Board::load(&b.path).map_err(|e| HwError::Other {
            device: "board".into(),
            message: e.to_string(),
        })?),
        None => all_sim.then(rigd_sim::Board::paper),
    };
    let axis_limits = axis_cfg.limits();
    let info = RigInfo {
        mode: if all_sim { "sim" } else { "hardware" }.into(),
        axis_limits_um: [axis_limits.min_um, axis_limits.max_um],
        piezo_limits_um: cfg.piezo.as_ref().map(|p| {
            let l = p.limits();
            [l.min_um, l.max_um]
        }),
        default_start_um: axis_cfg.scan_start_um(),
        scale_um_per_px: cfg.pipeline.scale_um_per_px,
        // How the mount turns axis travel into image motion ([pipeline] axis_dir).
        axis_dir: cfg.pipeline.axis_dir,
        frame_size: (cam_cfg.width, cam_cfg.height),
        // An all-sim rig runs the sim's XL-80; otherwise `[xl80]` names the log.
        interferometer: all_sim || cfg.xl80.is_some(),
        board,
        config: serde_json::to_value(cfg).unwrap_or_default(),
        job_defaults: cfg.job_defaults,
        grab_timeout_ms: cfg.frame_timeout_ms(),
    };
    if all_sim {
        let hw = open_sim_rig(cfg)?;
        let size = hw.camera.size();
        // The sim's XL-80 writes `[xl80] path` (or a temporary file), followed as on hardware.
        let log = match &cfg.xl80 {
            Some(x) => SimXl80::new(&hw.rig, Some(x.path.clone()), x.format, x.rtx_um_per_unit())?,
            None => SimXl80::new(&hw.rig, None, Xl80Format::Csv, 1000.0)?,
        };
        return Ok(Rig {
            info: RigInfo {
                frame_size: size,
                ..info
            },
            axis: Box::new(hw.axis),
            piezo: match cfg.piezo {
                Some(_) => Some(Box::new(hw.piezo)),
                None => None,
            },
            camera: Box::new(SimRigCamera::new(hw.rig, hw.camera)),
            log: Some(Box::new(log)),
        });
    }
    let axis = open_stage("axis", axis_cfg)?;
    let piezo = match &cfg.piezo {
        Some(p) => Some(open_stage("piezo", p)?),
        None => None,
    };
    let camera = open_camera(cam_cfg, cfg.board.as_ref().map(|b| b.path.as_path()))?;
    let log = cfg.xl80.as_ref().map(|x| -> Box<dyn PositionLog> {
        let f = Follower::new(&x.path, x.format).with_rtx_unit_um(x.rtx_um_per_unit());
        Box::new(FollowedLog::new(f, Duration::from_millis(x.poll_ms)))
    });
    Ok(Rig {
        info,
        axis,
        piezo,
        camera,
        log,
    })
}
