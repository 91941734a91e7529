//! The simulated rig `rigd --sim` runs when no better one is built in: a stage over
//! `rigd_sim::motion::Axis`, a camera that renders the paper's board from where the axis truly
//! is at the exposure instant, and an interferometer that reads the axis' true position.
//!
//! Faults can be injected (`rigd --sim --fault alarm@5`) to exercise the job's fault path.

use crate::daemon::rig::{PositionLog, Rig, RigInfo};
use crate::hw::{Camera, Frame, HwError, MotionState, Stage, StageStatus};
use rigd_sim::motion::{Axis, AxisParams};
use rigd_sim::render::{render_frame, View};
use rigd_sim::{Board, CameraModel};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

/// A fault to inject: what fails, and on which call (1-based) of the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// The axis raises a hard-limit alarm on its n-th move.
    Alarm(u32),
    /// The axis' serial port goes away on its n-th move.
    SerialLoss(u32),
    /// The camera stops delivering on its n-th grab.
    CameraTimeout(u32),
}

impl std::str::FromStr for Fault {
    type Err = String;
    fn from_str(s: &str) -> Result<Fault, String> {
        let (kind, n) = s
            .split_once('@')
            .ok_or_else(|| format!("fault {s:?}: expected KIND@N, e.g. alarm@5"))?;
        let n: u32 = n
            .parse()
            .map_err(|_| format!("fault {s:?}: {n:?} is not a call number"))?;
        match kind {
            "alarm" => Ok(Fault::Alarm(n)),
            "serial-loss" => Ok(Fault::SerialLoss(n)),
            "camera-timeout" => Ok(Fault::CameraTimeout(n)),
            _ => Err(format!(
                "fault {s:?}: unknown kind {kind:?} (alarm, serial-loss, camera-timeout)"
            )),
        }
    }
}

/// Settings of the simulated rig.
#[derive(Debug, Clone)]
pub struct SimSettings {
    pub axis: AxisParams,
    pub camera: CameraModel,
    pub board: Board,
    pub faults: Vec<Fault>,
}

impl Default for SimSettings {
    fn default() -> Self {
        SimSettings {
            // A fast axis and frame clock, so the demo's 620 frames fit in well under a minute.
            axis: AxisParams {
                max_speed_um_s: 50_000.0,
                accel_um_s2: 2_000_000.0,
                ..AxisParams::default()
            },
            camera: CameraModel {
                frame_period_ms: 5.0,
                exposure_ms: 2.0,
                supersample: 4,
                ..CameraModel::default()
            },
            board: Board::paper(),
            faults: Vec::new(),
        }
    }
}

/// Build the simulated rig.
pub fn sim_rig(s: &SimSettings) -> Rig {
    let axis = Arc::new(Axis::new(s.axis.clone()));
    axis.set_position(0.0);
    let piezo = Arc::new(Axis::new(AxisParams {
        max_speed_um_s: 10_000.0,
        accel_um_s2: 1_000_000.0,
        position_error_rms_um: 0.05,
        hard_min_um: 0.0,
        hard_max_um: 1_500.0,
        seed: s.axis.seed + 1,
    }));
    let alarm_at = s.faults.iter().find_map(|f| match f {
        Fault::Alarm(n) => Some(*n),
        _ => None,
    });
    let loss_at = s.faults.iter().find_map(|f| match f {
        Fault::SerialLoss(n) => Some(*n),
        _ => None,
    });
    let timeout_at = s.faults.iter().find_map(|f| match f {
        Fault::CameraTimeout(n) => Some(*n),
        _ => None,
    });
    let info = RigInfo {
        mode: "sim".into(),
        axis_limits_um: [0.0, 250_000.0],
        piezo_limits_um: Some([0.0, 1_400.0]),
        default_start_um: 1_000.0,
        scale_um_per_px: s.camera.scale_um_per_px,
        axis_dir: [-1.0, 0.0],
        frame_size: (s.camera.width, s.camera.height),
        board: Some(s.board.clone()),
        config: serde_json::json!({
            "sim": true,
            "axis": s.axis,
            "camera": s.camera,
            "board": s.board.name,
            "faults": s.faults.iter().map(|f| format!("{f:?}")).collect::<Vec<_>>(),
        }),
    };
    Rig {
        info,
        axis: Box::new(SimStage::new("axis", axis.clone(), alarm_at, loss_at)),
        piezo: Some(Box::new(SimStage::new("piezo", piezo.clone(), None, None))),
        camera: Box::new(SimCam {
            axis: axis.clone(),
            piezo,
            model: s.camera.clone(),
            board: s.board.clone(),
            sequence: 0,
            grabs: AtomicU32::new(0),
            timeout_at,
        }),
        log: Some(Box::new(SimInterferometer { axis })),
    }
}

/// A stage over a simulated axis.
pub struct SimStage {
    name: String,
    axis: Arc<Axis>,
    moves: u32,
    alarm_at: Option<u32>,
    loss_at: Option<u32>,
    alarmed: bool,
    gone: bool,
}

impl SimStage {
    pub fn new(name: &str, axis: Arc<Axis>, alarm_at: Option<u32>, loss_at: Option<u32>) -> Self {
        SimStage {
            name: name.into(),
            axis,
            moves: 0,
            alarm_at,
            loss_at,
            alarmed: false,
            gone: false,
        }
    }

    fn check(&self) -> Result<(), HwError> {
        if self.gone {
            return Err(HwError::PortGone {
                device: self.name.clone(),
                message: "the serial port closed (injected)".into(),
            });
        }
        if self.alarmed {
            return Err(HwError::Alarm {
                device: self.name.clone(),
                code: 1,
                message: "hard limit triggered; reset and home".into(),
            });
        }
        Ok(())
    }
}

impl Stage for SimStage {
    fn name(&self) -> &str {
        &self.name
    }
    fn move_rel(&mut self, delta_um: f64) -> Result<(), HwError> {
        let here = self.axis.reported_um(Instant::now());
        self.move_abs(here + delta_um)
    }
    fn move_abs(&mut self, target_um: f64) -> Result<(), HwError> {
        self.check()?;
        self.moves += 1;
        if self.loss_at == Some(self.moves) {
            self.gone = true;
            self.axis.stop();
            return self.check();
        }
        if self.alarm_at == Some(self.moves) {
            self.alarmed = true;
            self.axis.stop();
            return self.check();
        }
        self.axis
            .command_move(target_um)
            .map(|_| ())
            .map_err(|e| HwError::Limit {
                device: self.name.clone(),
                target_um,
                reason: e.to_string(),
            })
    }
    fn wait_settled(&mut self, timeout: Duration) -> Result<f64, HwError> {
        self.check()?;
        let end = self.axis.move_ends_at();
        let now = Instant::now();
        if end > now + timeout {
            return Err(HwError::Timeout {
                device: self.name.clone(),
                timeout_ms: timeout.as_millis() as u64,
                waiting_for: "end of move".into(),
            });
        }
        std::thread::sleep(end.saturating_duration_since(now));
        Ok(self.axis.reported_um(Instant::now()))
    }
    fn position_um(&mut self) -> Result<f64, HwError> {
        self.check()?;
        Ok(self.axis.reported_um(Instant::now()))
    }
    fn stop(&mut self) -> Result<(), HwError> {
        // A real controller still halts on a feed hold while alarmed: stop the axis first.
        self.axis.stop();
        Ok(())
    }
    fn home(&mut self) -> Result<(), HwError> {
        self.check()?;
        self.axis.set_position(0.0);
        Ok(())
    }
    fn status(&mut self) -> Result<StageStatus, HwError> {
        self.check()?;
        let now = Instant::now();
        Ok(StageStatus {
            state: if self.axis.is_moving(now) {
                MotionState::Moving
            } else {
                MotionState::Idle
            },
            position_um: self.axis.reported_um(now),
        })
    }
}

/// A camera on a frame clock that renders the board from the true axis position.
pub struct SimCam {
    axis: Arc<Axis>,
    piezo: Arc<Axis>,
    model: CameraModel,
    board: Board,
    sequence: u64,
    grabs: AtomicU32,
    timeout_at: Option<u32>,
}

impl SimCam {
    fn expose(&mut self, not_before: SystemTime, timeout: Duration) -> Result<Frame, HwError> {
        let n = self.grabs.fetch_add(1, Ordering::Relaxed) + 1;
        if self.timeout_at.is_some_and(|t| n >= t) {
            std::thread::sleep(timeout.min(Duration::from_millis(50)));
            return Err(HwError::Timeout {
                device: "camera".into(),
                timeout_ms: timeout.as_millis() as u64,
                waiting_for: "a frame (injected)".into(),
            });
        }
        // The next frame of the clock that starts at or after `not_before`.
        let period = Duration::from_secs_f64(self.model.frame_period_ms / 1000.0);
        let wait = not_before
            .duration_since(SystemTime::now())
            .unwrap_or_default();
        let wall = SystemTime::now() + wait;
        let since_epoch = wall
            .duration_since(SystemTime::UNIX_EPOCH)
            .unwrap_or_default();
        let phase =
            Duration::from_nanos((since_epoch.as_nanos() % period.as_nanos().max(1)) as u64);
        let to_next = if phase.is_zero() {
            Duration::ZERO
        } else {
            period - phase
        };
        std::thread::sleep(wait + to_next);
        let exposed = SystemTime::now();
        let mid = Instant::now() + Duration::from_secs_f64(self.model.exposure_ms / 2000.0);
        let x = self.axis.position_at(mid) + self.piezo.position_at(mid);
        self.sequence += 1;
        let image = render_frame(
            &self.board,
            &self.model,
            &View::at([x, 0.0]),
            1.0,
            self.sequence,
        );
        Ok(Frame {
            image,
            sequence: self.sequence,
            timestamp: exposed,
        })
    }
}

impl Camera for SimCam {
    fn name(&self) -> &str {
        "sim-camera"
    }
    fn size(&self) -> (u32, u32) {
        (self.model.width, self.model.height)
    }
    fn grab(&mut self, timeout: Duration) -> Result<Frame, HwError> {
        self.expose(SystemTime::now(), timeout)
    }
    fn grab_fresh(&mut self, not_before: SystemTime, timeout: Duration) -> Result<Frame, HwError> {
        self.expose(not_before, timeout)
    }
}

/// The interferometer of the simulated rig: the axis' true position.
pub struct SimInterferometer {
    axis: Arc<Axis>,
}

impl PositionLog for SimInterferometer {
    fn position_at(&mut self, t: SystemTime) -> Option<f64> {
        // Map the wall-clock instant onto the monotonic clock the axis runs on.
        let now_sys = SystemTime::now();
        let now = Instant::now();
        let at = match now_sys.duration_since(t) {
            Ok(ago) => now.checked_sub(ago)?,
            Err(e) => now + e.duration(),
        };
        Some(self.axis.position_at(at))
    }
}
