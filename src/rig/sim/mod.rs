//! The simulated rig `rigd --sim` runs: the whole `rigd_sim::SimRig` driven through the same
//! drivers a real rig uses. The axis is moved by rigd's GRBL driver over the real serialport
//! path to the GRBL emulator on a pseudo-terminal, the piezo by the GCS driver to the PI GCS
//! emulator; the camera is the rig's frame-clock camera (frames show where the line of sight
//! truly was during the exposure, motion blur included); the simulated XL-80 writes its live
//! log to a file that the daemon follows as it would a real one (`rig::FollowedLog`).
//!
//! Faults can be injected (`rigd --sim --fault alarm@5`): alarms and serial loss through the
//! GRBL emulator's own fault injection, camera timeouts through the frame-clock camera's
//! (its stream stalls; the driver's deadline runs out).
//!
//! Also here: the in-process devices a config with `driver = "sim"` opens (`stage`, `camera`,
//! `from_config`) and the sim's XL-80 (`xl80`). The whole module is the cargo feature `sim`.

pub mod camera;
mod from_config;
pub mod stage;
pub mod xl80;

pub use camera::{SimCamera, SimRigCamera};
pub(crate) use from_config::{devices_from_config, open_camera, open_stage};
pub use from_config::{open_sim_rig, SimHardware};
pub use stage::SimStage;
pub use xl80::SimXl80;

use super::{Rig, RigInfo, RigMode};
use crate::hw::devices::{HwError, Stage, StageMachine, StageStatus};
use crate::hw::gcs::{GcsOptions, GcsStage};
use crate::hw::grbl::{GrblOptions, GrblStage};
use crate::hw::limits::TravelLimits;
use crate::xl80::Xl80Format;
use rigd_sim::gcs::{GcsSim, GcsSimOptions};
use rigd_sim::grbl::{GrblSim, GrblSimOptions};
use rigd_sim::motion::{Axis, AxisParams};
use rigd_sim::serve::Faults;
use rigd_sim::{CameraModel, SimRig, SimRigConfig};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

/// A fault to inject: what fails, and on which call (1-based) of the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// The axis raises a hard-limit alarm on its n-th move.
    Alarm(u32),
    /// The axis' serial port goes away on its n-th move.
    SerialLoss(u32),
    /// The camera's stream stalls from its n-th grab (until the driver restarts it).
    CameraTimeout(u32),
    /// The axis driver panics on its n-th move: a fault of the daemon's own code, to
    /// exercise how a panicking job is failed and the worker goes on.
    Panic(u32),
}

impl std::str::FromStr for Fault {
    type Err = String;
    fn from_str(s: &str) -> Result<Fault, String> {
        let (kind, n) = s
            .split_once('@')
            .ok_or_else(|| format!("fault {s:?}: expected KIND@N, e.g. alarm@5"))?;
        let n: u32 = n
            .parse()
            .ok()
            .filter(|&n| n >= 1)
            .ok_or_else(|| format!("fault {s:?}: {n:?} is not a call number (1, 2, ...)"))?;
        match kind {
            "alarm" => Ok(Fault::Alarm(n)),
            "serial-loss" => Ok(Fault::SerialLoss(n)),
            "camera-timeout" => Ok(Fault::CameraTimeout(n)),
            "panic" => Ok(Fault::Panic(n)),
            _ => Err(format!(
                "fault {s:?}: unknown kind {kind:?} (alarm, serial-loss, camera-timeout, panic)"
            )),
        }
    }
}

/// Settings of the simulated rig.
#[derive(Debug, Clone)]
pub struct SimSettings {
    pub axis: AxisParams,
    pub piezo: AxisParams,
    pub camera: CameraModel,
    /// Board file (`config/boards/*.toml`); none = the paper's board.
    pub board_file: Option<PathBuf>,
    /// Soft travel limits the drivers enforce.
    pub axis_limits_um: [f64; 2],
    pub piezo_limits_um: [f64; 2],
    /// Line-of-sight travel (board µm along x, y) per µm of piezo travel: across the
    /// axis's (+y) by default, so a grid over the axis and the piezo moves the image in 2-D.
    pub piezo_dir: [f64; 2],
    pub faults: Vec<Fault>,
    /// The camera's profile name (`CameraModel::profile`), when `camera` is one: the
    /// sessions and calibration records name it.
    pub camera_profile: Option<String>,
}

impl Default for SimSettings {
    fn default() -> Self {
        SimSettings {
            // A fast axis and frame clock, so the demo's 620 frames fit in about a minute.
            axis: AxisParams {
                max_speed_um_s: 50_000.0,
                accel_um_s2: 2_000_000.0,
                ..AxisParams::default()
            },
            piezo: AxisParams {
                max_speed_um_s: 10_000.0,
                accel_um_s2: 1_000_000.0,
                position_error_rms_um: 0.05,
                hard_min_um: 0.0,
                hard_max_um: 1_500.0,
                seed: 2,
            },
            camera: CameraModel {
                frame_period_ms: 5.0,
                exposure_ms: 2.0,
                supersample: 4,
                ..CameraModel::default()
            },
            board_file: None,
            axis_limits_um: [0.0, 250_000.0],
            piezo_limits_um: [0.0, 1_400.0],
            piezo_dir: [0.0, 1.0],
            faults: Vec::new(),
            camera_profile: None,
        }
    }
}

impl SimSettings {
    /// The sim with the camera of `profile` (`ideal`, `webcam`, `stress`) on a fast frame
    /// clock (5 ms frames; an exposure the profile's own), so a study takes about a minute.
    /// `rigd --sim --camera` and `rigctl demo --camera` both start their rig from it.
    pub fn for_camera(profile: &str) -> Result<SimSettings, rigd_sim::camera::CameraError> {
        let mut camera = CameraModel::profile(profile)?;
        camera.supersample = 4;
        match profile {
            "ideal" => (camera.frame_period_ms, camera.exposure_ms) = (5.0, 2.0),
            _ => camera.frame_period_ms = (camera.exposure_ms + 2.0).max(5.0),
        }
        Ok(SimSettings {
            camera,
            camera_profile: Some(profile.to_string()),
            ..SimSettings::default()
        })
    }
}

fn sim_error(device: &str, e: impl std::fmt::Display) -> HwError {
    HwError::Other {
        device: device.into(),
        message: e.to_string(),
    }
}

fn limits(device: &str, l: [f64; 2]) -> Result<TravelLimits, HwError> {
    TravelLimits::new(l[0], l[1], l[1] - l[0]).map_err(|e| sim_error(device, e))
}

/// Build the simulated rig: start the `SimRig`, serve its axis and piezo on two ptys and
/// connect rigd's drivers to them.
/// The simulated camera's output curve, as a user would configure it for that camera.
pub fn response(cam: &CameraModel) -> crate::pipeline::Response {
    match cam.gamma {
        rigd_sim::camera::Gamma::Srgb => crate::pipeline::Response::Srgb,
        rigd_sim::camera::Gamma::Linear => crate::pipeline::Response::Linear,
    }
}

pub fn simulated(s: &SimSettings) -> Result<Rig, HwError> {
    simulated_with_truth(s).map(|(rig, _)| rig)
}

/// What the simulated stages truly do, whatever the drivers report (for tests).
pub struct SimTruth {
    pub axis: Arc<Axis>,
    pub piezo: Arc<Axis>,
}

/// [`simulated`], also handing out the simulated stages themselves.
pub fn simulated_with_truth(s: &SimSettings) -> Result<(Rig, SimTruth), HwError> {
    let rc = SimRigConfig {
        board_file: s.board_file.clone(),
        camera: s.camera.clone(),
        axis: s.axis.clone(),
        piezo: s.piezo.clone(),
        piezo_dir: s.piezo_dir,
        ..SimRigConfig::default()
    };
    let board = rc.board().map_err(|e| sim_error("sim-rig", e))?;
    let rig = SimRig::start(rc.clone()).map_err(|e| sim_error("sim-rig", e))?;
    let log = SimXl80::new(&rig, None, Xl80Format::Csv, 1000.0)?;
    let axis = emulated_axis(&rig, s)?;
    let piezo = emulated_piezo(&rig, s)?;
    if let Some(n) = s.fault_at(|f| match f {
        Fault::CameraTimeout(n) => Some(*n),
        _ => None,
    }) {
        rig.camera.stall_from_grab(n.into());
    }
    let truth = SimTruth {
        axis: Arc::clone(&rig.axis),
        piezo: Arc::clone(&rig.piezo),
    };
    let cam = SimCamera::new(Arc::clone(&rig.camera));
    let mut info = sim_info(s, &rc, board);
    info.axis_machine = axis.machine();
    let rig = Rig {
        info,
        axis: Box::new(axis),
        piezo: Some(Box::new(piezo)),
        camera: Box::new(SimRigCamera::new(rig, cam)),
        log: Some(Box::new(log)),
    };
    Ok((rig, truth))
}

impl SimSettings {
    /// The call number of the first fault `want` picks.
    fn fault_at(&self, want: fn(&Fault) -> Option<u32>) -> Option<u32> {
        self.faults.iter().find_map(want)
    }
}

/// The axis: the GRBL emulator on a pty, rigd's GRBL driver connected to it, the axis faults
/// armed.
fn emulated_axis(rig: &SimRig, s: &SimSettings) -> Result<EmulatedStage, HwError> {
    // Behind a stable link: the port that comes back after a serial loss has a new pty.
    let dir = LinkDir::new().map_err(|e| sim_error("sim-grbl", e))?;
    let link = dir.0.join("grbl");
    let grbl = GrblSim::spawn(
        Arc::clone(&rig.axis),
        GrblSimOptions::default(),
        Some(&link),
    )
    .map_err(|e| sim_error("sim-grbl", e))?;
    let mut go = GrblOptions::new(
        grbl.path().to_string_lossy(),
        limits("axis", s.axis_limits_um)?,
    );
    go.feed_um_s = s.axis.max_speed_um_s;
    go.status_poll_hz = crate::hw::grbl::EMULATOR_POLL_HZ;
    go.reply_timeout_ms = EMULATOR_REPLY_TIMEOUT_MS;
    let axis = GrblStage::connect("axis", go)?;
    Ok(EmulatedStage {
        faults: grbl.faults().clone(),
        stage: Box::new(axis),
        _emulator: Box::new((grbl, dir)),
        moves: 0,
        alarm_at: s.fault_at(|f| match f {
            Fault::Alarm(n) => Some(*n),
            _ => None,
        }),
        loss_at: s.fault_at(|f| match f {
            Fault::SerialLoss(n) => Some(*n),
            _ => None,
        }),
        panic_at: s.fault_at(|f| match f {
            Fault::Panic(n) => Some(*n),
            _ => None,
        }),
    })
}

/// How long the drivers wait for an emulated controller's reply. A real controller answers
/// in milliseconds from its own processor (the drivers' default, 1 s, is for it); the
/// emulators are threads of this process, and on a loaded machine the renderer and the
/// pipeline can keep them off a core for longer.
const EMULATOR_REPLY_TIMEOUT_MS: u64 = 5_000;

/// The piezo: the PI GCS emulator on a pty and rigd's GCS driver connected to it.
fn emulated_piezo(rig: &SimRig, s: &SimSettings) -> Result<EmulatedStage, HwError> {
    let gcs = GcsSim::spawn(Arc::clone(&rig.piezo), GcsSimOptions::default(), None)
        .map_err(|e| sim_error("sim-gcs", e))?;
    let mut po = GcsOptions::new(
        gcs.path().to_string_lossy(),
        limits("piezo", s.piezo_limits_um)?,
    );
    po.reply_timeout_ms = EMULATOR_REPLY_TIMEOUT_MS;
    let piezo = GcsStage::connect("piezo", po)?;
    Ok(EmulatedStage {
        faults: gcs.faults().clone(),
        stage: Box::new(piezo),
        _emulator: Box::new(gcs),
        moves: 0,
        alarm_at: None,
        loss_at: None,
        panic_at: None,
    })
}

/// What the daemon knows of the simulated rig up front.
fn sim_info(s: &SimSettings, rc: &SimRigConfig, board: crate::board::Board) -> RigInfo {
    RigInfo {
        mode: RigMode::Sim,
        axis_limits_um: s.axis_limits_um,
        piezo_limits_um: Some(s.piezo_limits_um),
        // The drivers' step limit is the whole travel: no step within it is refused.
        axis_max_step_um: None,
        piezo_max_step_um: None,
        axis_settle_ms: None,
        piezo_settle_ms: None,
        default_start_um: 1_000.0,
        scale_um_per_px: s.camera.scale_um_per_px,
        // The camera rides the axis: the board moves the other way in the image.
        axis_dir: [-rc.axis_dir[0], -rc.axis_dir[1]],
        piezo_dir: Some([-rc.piezo_dir[0], -rc.piezo_dir[1]]),
        frame_size: (s.camera.width, s.camera.height),
        response: response(&s.camera),
        // Not the renderer's print statistics: the calibration scan learns them.
        ink_prior: None,
        interferometer: true,
        axis_machine: None,
        config: serde_json::json!({
            "sim": true,
            "axis": s.axis,
            "piezo": s.piezo,
            "camera": s.camera,
            "camera_profile": s.camera_profile,
            "board": board.name,
            "axis_driver": "grbl (emulated, pty)",
            "piezo_driver": "gcs (emulated, pty)",
            "xl80": rigd_sim::xl80::Xl80Params {
                sample_rate_hz: xl80::SIM_RATE_HZ,
                ..rc.xl80.clone()
            },
            "xl80_log": "live CSV in a temporary file, a new capture per job, followed",
            "faults": s.faults.iter().map(|f| format!("{f:?}")).collect::<Vec<_>>(),
        }),
        board: Some(board),
        // The protocol's own defaults; `rigd --sim --grab-timeout-ms` may shorten the grab's.
        job_defaults: Default::default(),
        grab_timeout_ms: super::DEFAULT_GRAB_TIMEOUT_MS,
    }
}

/// A private folder for the emulators' port links, removed with the rig.
struct LinkDir(PathBuf);

impl LinkDir {
    fn new() -> std::io::Result<LinkDir> {
        static N: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let n = N.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        let dir = std::env::temp_dir().join(format!("rigd-sim-ports-{}-{n}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir(&dir)?;
        Ok(LinkDir(dir))
    }
}

impl Drop for LinkDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A driver connected to an emulated controller, which it keeps alive; arms the
/// emulator's fault injection on the configured move. A port lost by `serial-loss@N`
/// comes back when `reconnect` is asked for, as if plugged in again.
struct EmulatedStage {
    // Dropped before the emulator: the driver closes its port first.
    stage: Box<dyn Stage>,
    _emulator: Box<dyn Send>,
    faults: Faults,
    moves: u32,
    alarm_at: Option<u32>,
    loss_at: Option<u32>,
    panic_at: Option<u32>,
}

impl EmulatedStage {
    /// Count a move and arm the fault due on it.
    fn arm(&mut self) {
        self.moves += 1;
        if self.panic_at == Some(self.moves) {
            panic!("injected panic on move {}", self.moves);
        }
        if self.alarm_at == Some(self.moves) {
            self.faults.update(|p| p.alarm_mid_move = true);
        }
        if self.loss_at == Some(self.moves) {
            self.faults.vanish();
            // The emulator thread closes the pty master on its next turn.
            std::thread::sleep(Duration::from_millis(30));
        }
    }
}

impl Stage for EmulatedStage {
    fn name(&self) -> &str {
        self.stage.name()
    }
    fn move_rel(&mut self, delta_um: f64) -> Result<(), HwError> {
        self.arm();
        self.stage.move_rel(delta_um)
    }
    fn move_abs(&mut self, target_um: f64) -> Result<(), HwError> {
        self.arm();
        self.stage.move_abs(target_um)
    }
    fn wait_settled(&mut self, timeout: Duration) -> Result<f64, HwError> {
        self.stage.wait_settled(timeout)
    }
    fn position_um(&mut self) -> Result<f64, HwError> {
        self.stage.position_um()
    }
    fn stop(&mut self) -> Result<(), HwError> {
        self.stage.stop()
    }
    fn home(&mut self) -> Result<(), HwError> {
        self.stage.home()
    }
    fn home_stoppable(&mut self, stopped: &dyn Fn() -> bool) -> Result<bool, HwError> {
        self.stage.home_stoppable(stopped)
    }
    fn status(&mut self) -> Result<StageStatus, HwError> {
        self.stage.status()
    }
    fn unlock(&mut self) -> Result<(), HwError> {
        self.stage.unlock()
    }
    fn machine(&self) -> Option<StageMachine> {
        self.stage.machine()
    }
    fn planned_move(&self) -> Option<Duration> {
        self.stage.planned_move()
    }
    fn reconnect(&mut self) -> Result<(), HwError> {
        if self.loss_at.is_some_and(|n| n <= self.moves) {
            self.faults.restore();
            // The emulator thread opens the new pty on its next turn.
            std::thread::sleep(Duration::from_millis(30));
        }
        self.stage.reconnect()
    }
}
