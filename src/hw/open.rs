//! Open the configured hardware: one place that turns a config section into a driver, for
//! `rigctl hw` and the daemon alike.

use super::gcs::GcsStage;
use super::grbl::GrblStage;
use super::sim_camera::SimCamera;
use super::sim_stage::SimStage;
use super::{Camera, Frame, HwError, Stage};
use crate::config::{CameraConfig, CameraDriver, StageConfig, StageDriver};
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

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
        StageDriver::Sim => {
            let limits = cfg.limits();
            limits.validate().map_err(invalid)?;
            let axis = Arc::new(rigd_sim::motion::Axis::new(
                cfg.sim.clone().unwrap_or_default(),
            ));
            Ok(Box::new(SimStage::new(name, axis, limits)))
        }
    }
}

/// The simulated camera together with the simulated rig it watches (kept alive with it).
pub struct SimRigCamera {
    _rig: rigd_sim::SimRig,
    cam: SimCamera,
}

impl SimRigCamera {
    pub fn new(rig: rigd_sim::SimRig, cam: SimCamera) -> SimRigCamera {
        SimRigCamera { _rig: rig, cam }
    }
}

impl Camera for SimRigCamera {
    fn name(&self) -> &str {
        self.cam.name()
    }
    fn size(&self) -> (u32, u32) {
        self.cam.size()
    }
    fn grab(&mut self, timeout: Duration) -> Result<Frame, HwError> {
        self.cam.grab(timeout)
    }
    fn grab_fresh(&mut self, not_before: SystemTime, timeout: Duration) -> Result<Frame, HwError> {
        self.cam.grab_fresh(not_before, timeout)
    }
}

/// Open the camera. `board` is the board file the simulated camera renders (none: the
/// paper's board); a real camera ignores it. With `driver = "v4l2"` in a build without the
/// `v4l2` feature this is an error that says how to rebuild.
pub fn open_camera(cfg: &CameraConfig, board: Option<&Path>) -> Result<Box<dyn Camera>, HwError> {
    match cfg.driver {
        CameraDriver::V4l2 => open_v4l2(cfg),
        CameraDriver::Sim => {
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
            let rig = rigd_sim::SimRig::start(rig_cfg).map_err(|e| HwError::Other {
                device: "sim-camera".into(),
                message: e.to_string(),
            })?;
            let cam = SimCamera::new(Arc::clone(&rig.camera));
            Ok(Box::new(SimRigCamera::new(rig, cam)))
        }
    }
}

#[cfg(feature = "v4l2")]
fn open_v4l2(cfg: &CameraConfig) -> Result<Box<dyn Camera>, HwError> {
    Ok(Box::new(super::v4l2::V4l2Camera::from_config(cfg)?))
}

#[cfg(not(feature = "v4l2"))]
fn open_v4l2(cfg: &CameraConfig) -> Result<Box<dyn Camera>, HwError> {
    Err(HwError::Other {
        device: cfg.device.clone().unwrap_or_default(),
        message: "this rigd was built without V4L2 support: rebuild with `cargo build --release --features v4l2` (needs libclang-dev)".into(),
    })
}

/// The whole simulated rig from a config, for `rigd --sim`: one `SimRig` whose camera watches
/// the same axis and piezo the stages move (opening them separately with `open_stage` and
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
pub fn open_sim_rig(cfg: &crate::config::Config) -> Result<SimHardware, HwError> {
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
        None => super::limits::TravelLimits {
            min_um: p.hard_min_um,
            max_um: p.hard_max_um,
            max_step_um: p.hard_max_um - p.hard_min_um,
        },
    };
    let (axis_limits, piezo_limits) = (limits(&cfg.axis, &rc.axis), limits(&cfg.piezo, &rc.piezo));
    let rig = rigd_sim::SimRig::start(rc).map_err(|e| HwError::Other {
        device: "sim-rig".into(),
        message: e.to_string(),
    })?;
    Ok(SimHardware {
        axis: SimStage::new("axis", Arc::clone(&rig.axis), axis_limits),
        piezo: SimStage::new("piezo", Arc::clone(&rig.piezo), piezo_limits),
        camera: SimCamera::new(Arc::clone(&rig.camera)),
        rig,
    })
}
