//! The simulated devices a config's `driver = "sim"` sections open: in-process (no pty), from
//! `[axis.sim]`/`[piezo.sim]` kinematics and the `[camera.sim]` model.

use super::{SimCamera, SimRigCamera, SimStage, SimXl80};
use crate::config::{CameraConfig, Config, StageConfig};
use crate::hw::devices::{Camera, HwError, Stage};
use crate::hw::limits::TravelLimits;
use crate::rig::open::Devices;
use crate::xl80::Xl80Format;
use std::path::Path;
use std::sync::Arc;

fn sim_error(device: &str, e: impl std::fmt::Display) -> HwError {
    HwError::Other {
        device: device.into(),
        message: e.to_string(),
    }
}

/// A stand-alone simulated stage: a fresh simulated axis at 0 (for `rigctl hw` bring-up).
pub(crate) fn open_stage(name: &str, cfg: &StageConfig) -> Result<Box<dyn Stage>, HwError> {
    let limits = cfg.limits();
    limits.validate().map_err(|e| sim_error(name, e))?;
    let axis = Arc::new(rigd_sim::motion::Axis::new(
        cfg.sim.clone().unwrap_or_default(),
    ));
    Ok(Box::new(SimStage::new(name, axis, limits)))
}

/// A stand-alone simulated camera on a simulated rig of its own, rendering `board` (none: the
/// paper's board).
pub(crate) fn open_camera(
    cfg: &CameraConfig,
    board: Option<&Path>,
) -> Result<Box<dyn Camera>, HwError> {
    let mut model = cfg.sim.clone().unwrap_or_default();
    if cfg.sim.is_none() {
        model.width = cfg.width;
        model.height = cfg.height;
    }
    let rig_cfg = rigd_sim::SimRigConfig {
        board_file: board.map(Path::to_path_buf),
        camera: model,
        ..Default::default()
    };
    let rig = rigd_sim::SimRig::start(rig_cfg).map_err(|e| sim_error("sim-camera", e))?;
    let cam = SimCamera::new(Arc::clone(&rig.camera));
    Ok(Box::new(SimRigCamera::new(rig, cam)))
}

/// The whole simulated rig of a config, in process: one `SimRig` whose camera watches the
/// same axis and piezo the stages move (opening them separately with `open_stage` and
/// `open_camera` gives independent simulations, fine for bring-up, not for jobs).
pub struct SimHardware {
    pub axis: SimStage,
    pub piezo: SimStage,
    pub camera: SimCamera,
    /// The rig itself (its XL-80 log can be started with `rig.start_xl80_log`).
    pub rig: rigd_sim::SimRig,
}

/// Build [`SimHardware`]: kinematics from `[axis.sim]`/`[piezo.sim]`, the camera model from
/// `[camera.sim]` (or the sim defaults at `[camera]` width x height), the board from
/// `[board]`, soft limits from the sections (the hard limits when a section is absent).
pub fn open_sim_rig(cfg: &Config) -> Result<SimHardware, HwError> {
    let mut rc = rigd_sim::SimRigConfig {
        board_file: cfg.board.as_ref().map(|b| b.path.clone()),
        ..Default::default()
    };
    if let Some(a) = cfg.axis.as_ref().and_then(|a| a.sim.clone()) {
        rc.axis = a;
    }
    if let Some(p) = cfg.piezo.as_ref().and_then(|p| p.sim.clone()) {
        rc.piezo = p;
    }
    // The line of sight moves against the image ([pipeline] piezo_dir is the image's).
    if let Some([x, y]) = cfg.pipeline.piezo_dir {
        rc.piezo_dir = [-x, -y];
    }
    if let Some(c) = &cfg.camera {
        match &c.sim {
            Some(m) => rc.camera = m.clone(),
            None => {
                rc.camera.width = c.width;
                rc.camera.height = c.height;
            }
        }
    }
    let limits = |sec: &Option<StageConfig>, p: &rigd_sim::motion::AxisParams| match sec {
        Some(s) => s.limits(),
        None => TravelLimits {
            min_um: p.hard_min_um,
            max_um: p.hard_max_um,
            max_step_um: p.hard_max_um - p.hard_min_um,
        },
    };
    let (axis_limits, piezo_limits) = (limits(&cfg.axis, &rc.axis), limits(&cfg.piezo, &rc.piezo));
    let rig = rigd_sim::SimRig::start(rc).map_err(|e| sim_error("sim-rig", e))?;
    Ok(SimHardware {
        axis: SimStage::new("axis", Arc::clone(&rig.axis), axis_limits),
        piezo: SimStage::new("piezo", Arc::clone(&rig.piezo), piezo_limits),
        camera: SimCamera::new(Arc::clone(&rig.camera)),
        rig,
    })
}

/// An all-"sim" config's devices for `rig::from_config`: [`open_sim_rig`], and the sim's
/// XL-80 writing `[xl80] path` (or a temporary file), followed as on hardware.
pub(crate) fn devices_from_config(cfg: &Config) -> Result<Devices, HwError> {
    let hw = open_sim_rig(cfg)?;
    let log = match &cfg.xl80 {
        Some(x) => SimXl80::new(&hw.rig, Some(x.path.clone()), x.format, x.rtx_um_per_unit())?,
        None => SimXl80::new(&hw.rig, None, Xl80Format::Csv, 1000.0)?,
    };
    Ok(Devices {
        axis: Box::new(hw.axis),
        piezo: match cfg.piezo {
            Some(_) => Some(Box::new(hw.piezo)),
            None => None,
        },
        camera: Box::new(SimRigCamera::new(hw.rig, hw.camera)),
        log: Some(Box::new(log)),
    })
}
