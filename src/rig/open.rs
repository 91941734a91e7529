//! The rig `rigd --config FILE` runs, and the devices `rigctl hw` talks to: a config's
//! `[axis]`, `[piezo]`, `[camera]`, `[board]` and `[xl80]` turned into drivers, their options
//! converted from the config here (the drivers know nothing of it). When every device's
//! driver is "sim" the devices are one simulated rig (`rig::sim`), so the camera sees the
//! stages move.

use super::{FollowedLog, Rig, RigInfo, RigMode};
use crate::acquisition::Processing;
use crate::board::Board;
use crate::config::{CameraConfig, CameraDriver, Config, PipelineConfig, StageConfig, StageDriver};
use crate::hw::devices::{Camera, HwError, PositionLog, Stage};
use crate::hw::gcs::GcsStage;
use crate::hw::grbl::GrblStage;
use std::path::Path;
use std::time::Duration;

/// A rig's devices, before its [`RigInfo`] is made from them.
pub(crate) struct Devices {
    pub axis: Box<dyn Stage>,
    pub piezo: Option<Box<dyn Stage>>,
    pub camera: Box<dyn Camera>,
    pub log: Option<Box<dyn PositionLog>>,
}

fn missing(section: &str, cfg: &Config) -> HwError {
    HwError::Other {
        device: section.trim_matches(['[', ']']).into(),
        message: format!(
            "{}: the daemon needs a {section} section",
            cfg.source.display()
        ),
    }
}

/// The error for a "sim" driver in a build without the simulator.
#[cfg(not(feature = "sim"))]
pub(crate) fn no_sim(device: &str) -> HwError {
    HwError::Other {
        device: device.into(),
        message: "driver = \"sim\": rigd was built without the `sim` feature (rebuild with \
                  default features, or `--features sim`)"
            .into(),
    }
}

/// Build the rig a config describes, connecting to its devices now.
pub fn from_config(cfg: &Config) -> Result<Rig, HwError> {
    let axis_cfg = cfg.axis.as_ref().ok_or_else(|| missing("[axis]", cfg))?;
    let cam_cfg = cfg
        .camera
        .as_ref()
        .ok_or_else(|| missing("[camera]", cfg))?;
    // Without the simulator an all-"sim" config goes the hardware way, whose sim arms refuse.
    let all_sim = cfg!(feature = "sim")
        && axis_cfg.driver == StageDriver::Sim
        && cfg
            .piezo
            .as_ref()
            .is_none_or(|p| p.driver == StageDriver::Sim)
        && cam_cfg.driver == CameraDriver::Sim;
    let board = match &cfg.board {
        Some(b) => Some(Board::load(&b.path).map_err(|e| HwError::Other {
            device: "board".into(),
            message: e.to_string(),
        })?),
        None => all_sim.then(Board::paper),
    };
    let devices = if all_sim {
        sim_devices(cfg)?
    } else {
        hardware_devices(cfg, axis_cfg, cam_cfg)?
    };
    let piezo_cfg = cfg.piezo.as_ref();
    let settle = |s: &StageConfig| (s.settle_ms > 0).then_some(s.settle_ms);
    let info = RigInfo {
        mode: if all_sim {
            RigMode::Sim
        } else {
            RigMode::Hardware
        },
        axis_limits_um: [axis_cfg.soft_min_um, axis_cfg.soft_max_um],
        piezo_limits_um: piezo_cfg.map(|p| [p.soft_min_um, p.soft_max_um]),
        axis_max_step_um: Some(axis_cfg.max_step_um),
        piezo_max_step_um: piezo_cfg.map(|p| p.max_step_um),
        axis_settle_ms: settle(axis_cfg),
        piezo_settle_ms: piezo_cfg.and_then(settle),
        default_start_um: axis_cfg.scan_start_um(),
        scale_um_per_px: cfg.pipeline.scale_um_per_px,
        // How the mount turns axis travel into image motion ([pipeline] axis_dir).
        axis_dir: cfg.pipeline.axis_dir,
        piezo_dir: cfg.pipeline.piezo_dir,
        // What the camera delivers (a V4L2 driver may adjust the configured size).
        frame_size: devices.camera.size(),
        response: camera_response(cam_cfg),
        ink_prior: camera_ink_prior(cam_cfg),
        // An all-sim rig runs the sim's XL-80; otherwise `[xl80]` names the log.
        interferometer: devices.log.is_some(),
        axis_machine: devices.axis.machine(),
        board,
        config: serde_json::to_value(cfg).unwrap_or_default(),
        job_defaults: job_defaults(&cfg.pipeline),
        grab_timeout_ms: cfg.frame_timeout_ms(),
    };
    let Devices {
        axis,
        piezo,
        camera,
        log,
    } = devices;
    Ok(Rig {
        info,
        axis,
        piezo,
        camera,
        log,
    })
}

#[cfg(feature = "sim")]
fn sim_devices(cfg: &Config) -> Result<Devices, HwError> {
    super::sim::devices_from_config(cfg)
}

#[cfg(not(feature = "sim"))]
fn sim_devices(_cfg: &Config) -> Result<Devices, HwError> {
    Err(no_sim("axis"))
}

/// Each device through its own driver; the interferometer follows `[xl80] path`.
fn hardware_devices(
    cfg: &Config,
    axis_cfg: &StageConfig,
    cam_cfg: &CameraConfig,
) -> Result<Devices, HwError> {
    let axis = open_stage("axis", axis_cfg)?;
    let piezo = match &cfg.piezo {
        Some(p) => Some(open_stage("piezo", p)?),
        None => None,
    };
    let camera = open_camera(cam_cfg, cfg.board.as_ref().map(|b| b.path.as_path()))?;
    let log = cfg.xl80.as_ref().map(|x| -> Box<dyn PositionLog> {
        Box::new(FollowedLog::new(
            x.follower(),
            Duration::from_millis(x.poll_ms),
        ))
    });
    Ok(Devices {
        axis,
        piezo,
        camera,
        log,
    })
}

/// `[pipeline]`'s processing defaults, as a job's processing settings: only the keys the
/// file sets.
fn job_defaults(p: &PipelineConfig) -> Processing {
    Processing {
        k: p.k,
        estimator: p.estimator,
        combine: p.combine,
        registration: p.registration.map(Into::into),
        whole_frame: p.whole_frame,
    }
}

/// Open a stage (`name` is "axis" or "piezo", used in messages). Serial drivers connect now
/// (GRBL waits for its banner); the sim driver starts a fresh simulated axis at 0.
pub fn open_stage(name: &str, cfg: &StageConfig) -> Result<Box<dyn Stage>, HwError> {
    let invalid = |message: String| HwError::Other {
        device: name.to_string(),
        message,
    };
    match cfg.driver {
        StageDriver::Grbl => {
            let o = cfg.grbl_options();
            o.validate().map_err(invalid)?;
            Ok(Box::new(GrblStage::connect(name, o)?))
        }
        StageDriver::Gcs => {
            let o = cfg.gcs_options();
            o.validate().map_err(invalid)?;
            Ok(Box::new(GcsStage::connect(name, o)?))
        }
        #[cfg(feature = "sim")]
        StageDriver::Sim => super::sim::open_stage(name, cfg),
        #[cfg(not(feature = "sim"))]
        StageDriver::Sim => Err(no_sim(name)),
    }
}

/// Open the camera. `board` is the board file the simulated camera renders (none: the
/// paper's board); a real camera ignores it. With `driver = "v4l2"` in a build without the
/// `v4l2` feature this is an error that says how to rebuild.
pub fn open_camera(cfg: &CameraConfig, board: Option<&Path>) -> Result<Box<dyn Camera>, HwError> {
    match cfg.driver {
        CameraDriver::V4l2 => open_v4l2(cfg),
        #[cfg(feature = "sim")]
        CameraDriver::Sim => super::sim::open_camera(cfg, board),
        #[cfg(not(feature = "sim"))]
        CameraDriver::Sim => {
            let _ = board;
            Err(no_sim("camera"))
        }
    }
}

/// The camera's output curve: `[camera] response`, else the sim camera's own, else sRGB (a
/// UVC webcam's).
fn camera_response(cfg: &CameraConfig) -> crate::pipeline::Response {
    if let Some(r) = cfg.response {
        return r;
    }
    match cfg.driver {
        #[cfg(feature = "sim")]
        CameraDriver::Sim => super::sim::response(&cfg.sim.clone().unwrap_or_default()),
        _ => crate::pipeline::Response::Srgb,
    }
}

/// `[camera] ink_prior`. (Not the sim's own print's: rigd learns those in its
/// calibration scan, as on a real rig.)
fn camera_ink_prior(cfg: &CameraConfig) -> Option<crate::pipeline::InkPrior> {
    cfg.ink_prior
}

#[cfg(feature = "v4l2")]
fn open_v4l2(cfg: &CameraConfig) -> Result<Box<dyn Camera>, HwError> {
    Ok(Box::new(crate::hw::v4l2::V4l2Camera::open(
        &cfg.v4l2_options(),
    )?))
}

#[cfg(not(feature = "v4l2"))]
fn open_v4l2(cfg: &CameraConfig) -> Result<Box<dyn Camera>, HwError> {
    Err(HwError::Other {
        device: cfg.v4l2_options().device,
        message: "this rigd was built without V4L2 support: install it with V4L2 support, from the clone: `cargo install --locked --path . --features v4l2` (needs libclang-dev)".into(),
    })
}
