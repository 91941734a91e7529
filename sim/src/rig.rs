//! The whole simulated rig in one process: the numerically controlled axis and the piezo
//! flexure (both `motion::Axis`, moving the camera's line of sight), the frame-clock camera
//! watching the board through them, and optionally a live XL-80 log of the same motion.
//!
//! Built from one serde config in which everything has a default (the paper's board, the
//! default camera), so `SimRig::start(SimRigConfig::default())` is a working rig.

use crate::board::{Board, BoardError};
use crate::camera::{CameraError, CameraModel};
use crate::camera_clock::FrameClockCamera;
use crate::frames::FrameRenderer;
use crate::motion::{Axis, AxisParams, Leadscrew, TruePosition};
use crate::xl80::{LiveLog, LiveOptions, LogFormat, LogSummary, Xl80Error, Xl80Params};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimRigConfig {
    /// Board file (`config/boards/*.toml`); none = the paper's board.
    pub board_file: Option<PathBuf>,
    pub camera: CameraModel,
    /// The numerically controlled axis (~2 µm positioning error, as the paper's).
    pub axis: AxisParams,
    /// The axis' leadscrew: its periodic error (none by default).
    pub leadscrew: Leadscrew,
    /// The piezo flexure: short travel, fast, closed-loop accurate.
    pub piezo: AxisParams,
    /// Line-of-sight travel (board µm along x, y) per µm of axis travel.
    pub axis_dir: [f64; 2],
    /// Line-of-sight travel per µm of piezo travel.
    pub piezo_dir: [f64; 2],
    /// Board point at the top-left corner of pixel (0, 0) with both stages at 0.
    pub origin_um: [f64; 2],
    /// Seed of the camera's random effects (flicker, vibration, noise).
    pub seed: u64,
    pub xl80: Xl80Params,
}

/// Piezo flexure defaults: 100 µm travel, millisecond moves, nanometre repeatability.
pub fn default_piezo() -> AxisParams {
    AxisParams {
        max_speed_um_s: 10_000.0,
        accel_um_s2: 10_000_000.0,
        position_error_rms_um: 0.01,
        hard_min_um: 0.0,
        hard_max_um: 100.0,
        seed: 2,
    }
}

impl Default for SimRigConfig {
    fn default() -> Self {
        SimRigConfig {
            board_file: None,
            camera: CameraModel::default(),
            axis: AxisParams::default(),
            leadscrew: Leadscrew::default(),
            piezo: default_piezo(),
            axis_dir: [1.0, 0.0],
            piezo_dir: [1.0, 0.0],
            origin_um: [0.0, 0.0],
            seed: 1,
            xl80: Xl80Params::default(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RigError {
    #[error(transparent)]
    Board(#[from] BoardError),
    #[error(transparent)]
    Camera(#[from] CameraError),
    #[error(transparent)]
    Xl80(#[from] Xl80Error),
    #[error("sim rig config {origin}: {message}")]
    Config { origin: String, message: String },
}

impl SimRigConfig {
    /// The default rig with the camera of profile `name` (`CameraModel::profile`); the
    /// `webcam` and `stress` rigs' axis also has a leadscrew error (`Leadscrew::webcam`).
    pub fn profile(name: &str) -> Result<SimRigConfig, RigError> {
        let camera = CameraModel::profile(name)?;
        let leadscrew = match name {
            "ideal" => Leadscrew::default(),
            _ => Leadscrew::webcam(),
        };
        Ok(SimRigConfig {
            camera,
            leadscrew,
            ..SimRigConfig::default()
        })
    }

    /// Parse a TOML sim config; `origin` names the source in errors.
    pub fn parse(text: &str, origin: &str) -> Result<SimRigConfig, RigError> {
        toml::from_str(text).map_err(|e| RigError::Config {
            origin: origin.to_string(),
            message: e.to_string(),
        })
    }

    pub fn board(&self) -> Result<Board, BoardError> {
        match &self.board_file {
            Some(p) => Board::load(p),
            None => Ok(Board::paper()),
        }
    }
}

/// Where the camera's line of sight is: axis and piezo travel combined.
pub struct LineOfSight {
    pub axis: Arc<Axis>,
    pub piezo: Arc<Axis>,
    pub axis_dir: [f64; 2],
    pub piezo_dir: [f64; 2],
}

impl TruePosition for LineOfSight {
    fn true_position_um(&self, t: Instant) -> [f64; 2] {
        let (a, p) = (self.axis.position_at(t), self.piezo.position_at(t));
        [
            a * self.axis_dir[0] + p * self.piezo_dir[0],
            a * self.axis_dir[1] + p * self.piezo_dir[1],
        ]
    }
}

/// A running simulated rig.
pub struct SimRig {
    pub axis: Arc<Axis>,
    pub piezo: Arc<Axis>,
    pub line_of_sight: Arc<LineOfSight>,
    pub camera: Arc<FrameClockCamera>,
    config: SimRigConfig,
    xl80: Option<LiveLog>,
}

impl SimRig {
    /// Build the rig and start the camera streaming.
    pub fn start(config: SimRigConfig) -> Result<SimRig, RigError> {
        let board = config.board()?;
        config.xl80.validate()?;
        let axis = Arc::new(Axis::new(config.axis.clone()).with_leadscrew(config.leadscrew));
        let piezo = Arc::new(Axis::new(config.piezo.clone()));
        let line_of_sight = Arc::new(LineOfSight {
            axis: Arc::clone(&axis),
            piezo: Arc::clone(&piezo),
            axis_dir: config.axis_dir,
            piezo_dir: config.piezo_dir,
        });
        let renderer = FrameRenderer::new(board, config.camera.clone(), config.seed)?
            .with_origin(config.origin_um);
        let camera = Arc::new(FrameClockCamera::start(
            renderer,
            Arc::clone(&line_of_sight) as Arc<dyn TruePosition>,
        ));
        Ok(SimRig {
            axis,
            piezo,
            line_of_sight,
            camera,
            config,
            xl80: None,
        })
    }

    pub fn config(&self) -> &SimRigConfig {
        &self.config
    }

    /// Start a live XL-80 log of the line of sight into `path` (a running one is finished
    /// first).
    pub fn start_xl80_log(
        &mut self,
        path: impl Into<PathBuf>,
        format: LogFormat,
    ) -> Result<Option<LogSummary>, RigError> {
        self.start_xl80_log_with(path, format, LiveOptions::default())
    }

    /// [`SimRig::start_xl80_log`] with [`LiveOptions`] (flush period, whole-second start).
    pub fn start_xl80_log_with(
        &mut self,
        path: impl Into<PathBuf>,
        format: LogFormat,
        opts: LiveOptions,
    ) -> Result<Option<LogSummary>, RigError> {
        let previous = self.finish_xl80_log()?;
        self.xl80 = Some(LiveLog::start_with(
            path,
            format,
            self.config.xl80.clone(),
            Arc::clone(&self.line_of_sight) as Arc<dyn TruePosition>,
            opts,
        )?);
        Ok(previous)
    }

    /// Stop the live XL-80 log and complete its file; `None` if none was running.
    pub fn finish_xl80_log(&mut self) -> Result<Option<LogSummary>, RigError> {
        match self.xl80.take() {
            Some(log) => Ok(Some(log.finish()?)),
            None => Ok(None),
        }
    }
}
