//! The rig's TOML configuration (`config/rigd.toml` documents every key).
//!
//! Every section is optional so a half-built rig can be brought up piece by piece with
//! `rigctl hw`; whoever needs a section asks for it with [`Config::axis`] & co., which name
//! the file and the missing section. Unknown keys are errors (a typo must not silently fall
//! back to a default on a metrology rig), and every error names the file and the key.

use crate::hw::gcs::GcsOptions;
use crate::hw::grbl::{GrblOptions, OnAlarm};
use crate::hw::limits::TravelLimits;
use crate::hw::pixfmt::PixelFormat;
use crate::hw::v4l2_options::V4l2Options;
use crate::pipeline::{Combine, Estimator, Registration};
pub use crate::xl80::Xl80Format;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// `[axis.sim]`/`[piezo.sim]`: the simulated axis' kinematics. Without the `sim` feature the
/// table is kept as plain data (a config naming driver "sim" is refused when opened).
#[cfg(feature = "sim")]
pub type SimAxisTable = rigd_sim::motion::AxisParams;
#[cfg(not(feature = "sim"))]
pub type SimAxisTable = toml::Table;
/// `[camera.sim]`: the simulated camera's model (plain data without the `sim` feature).
#[cfg(feature = "sim")]
pub type SimCameraTable = rigd_sim::CameraModel;
#[cfg(not(feature = "sim"))]
pub type SimCameraTable = toml::Table;

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The io error is part of the message, not a `source`: printed with its chain
    /// (`{:#}`) the cause would otherwise appear twice.
    #[error("{path}: cannot read: {error}")]
    Read {
        path: PathBuf,
        error: std::io::Error,
    },
    /// Syntax errors, unknown keys and wrong types: toml's message names the key and line.
    #[error("{path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("{path}: key `{key}`: {message}")]
    Invalid {
        path: PathBuf,
        key: String,
        message: String,
    },
    #[error("{path}: no [{section}] section (needed to {purpose})")]
    Missing {
        path: PathBuf,
        section: &'static str,
        purpose: String,
    },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Where the config was read from (not a key; set by [`Config::load`]).
    #[serde(skip)]
    pub source: PathBuf,
    /// The numerically controlled axis that carries the camera.
    pub axis: Option<StageConfig>,
    /// The piezo flexure (fine axis), if the rig has one.
    pub piezo: Option<StageConfig>,
    pub camera: Option<CameraConfig>,
    pub xl80: Option<Xl80Config>,
    #[serde(default)]
    pub daemon: DaemonSettings,
    pub board: Option<BoardConfig>,
    /// The rig's image geometry and the processing defaults of jobs that do not set their own.
    #[serde(default)]
    pub pipeline: PipelineConfig,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StageDriver {
    /// GRBL 1.1 over serial (G-code).
    Grbl,
    /// Physik Instrumente GCS over serial.
    Gcs,
    /// The simulated axis (no hardware).
    Sim,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StageConfig {
    pub driver: StageDriver,
    /// Serial port, e.g. `/dev/ttyUSB0` or `/dev/serial/by-id/...` (grbl and gcs).
    #[serde(default)]
    pub port: Option<String>,
    #[serde(default = "default_baud")]
    pub baud: u32,
    /// Soft travel limits, checked before anything moves.
    pub soft_min_um: f64,
    pub soft_max_um: f64,
    /// Largest single move accepted, absolute or relative: its distance from where the stage
    /// was last commanded to be (its target).
    pub max_step_um: f64,
    /// Deadline for one reply line.
    #[serde(default = "default_reply_timeout_ms")]
    pub reply_timeout_ms: u64,
    /// Deadline for a move to finish and settle.
    #[serde(default = "default_move_timeout_ms")]
    pub move_timeout_ms: u64,
    /// GRBL: deadline for the banner after the port is opened (opening resets the board).
    #[serde(default = "default_open_timeout_ms")]
    pub open_timeout_ms: u64,
    /// Deadline for the homing cycle (GRBL `$H`, GCS `FRF`).
    #[serde(default = "default_home_timeout_ms")]
    pub home_timeout_ms: u64,
    /// Extra wait after the controller reports the move done, before a frame counts as fresh.
    #[serde(default)]
    pub settle_ms: u64,
    /// GRBL: what to do when the controller is in alarm and a move is asked for.
    #[serde(default)]
    pub on_alarm: OnAlarm,
    /// GRBL: run the homing cycle (`$H`) right after connecting.
    #[serde(default)]
    pub home_on_connect: bool,
    /// GRBL: feed rate of moves, µm/s.
    #[serde(default = "default_feed_um_s")]
    pub feed_um_s: f64,
    /// GRBL: average rate of `?` status reports, Hz (at most 10; GRBL asks for 5).
    #[serde(default = "default_status_poll_hz")]
    pub status_poll_hz: f64,
    /// GCS: the axis identifier on the controller.
    #[serde(default = "default_gcs_axis")]
    pub gcs_axis: String,
    /// GCS: µm per controller position unit (PI piezo controllers: normally 1).
    #[serde(default = "default_um_per_unit")]
    pub um_per_unit: f64,
    /// GCS: switch the servo on when connecting.
    #[serde(default = "default_true")]
    pub servo_on_connect: bool,
    /// Where `home` moves (GCS; the sim stage), µm.
    #[serde(default)]
    pub home_um: f64,
    /// GCS: `home` runs the reference move `FRF` instead of moving to `home_um`.
    #[serde(default)]
    pub home_reference: bool,
    /// `[axis]` only: where a scan starts when a job gives no `start_um` (default: the
    /// soft minimum, or 0 if that is negative). Must lie within the soft limits.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub default_start_um: Option<f64>,
    /// sim: kinematics of the simulated axis (defaults when absent).
    #[serde(default)]
    pub sim: Option<SimAxisTable>,
}

fn default_baud() -> u32 {
    115_200
}
fn default_reply_timeout_ms() -> u64 {
    1_000
}
fn default_move_timeout_ms() -> u64 {
    30_000
}
fn default_open_timeout_ms() -> u64 {
    2_500
}
fn default_home_timeout_ms() -> u64 {
    60_000
}
fn default_feed_um_s() -> f64 {
    10_000.0
}
fn default_status_poll_hz() -> f64 {
    5.0
}
fn default_um_per_unit() -> f64 {
    1.0
}
fn default_true() -> bool {
    true
}
fn default_gcs_axis() -> String {
    "1".to_string()
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CameraDriver {
    V4l2,
    Sim,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    pub driver: CameraDriver,
    /// v4l2: a device path (`/dev/video0`, `/dev/v4l/by-id/...`) or the device's name as
    /// `rigctl hw cameras` lists it (matched case-insensitively, first match).
    #[serde(default)]
    pub device: Option<String>,
    #[serde(default = "default_width")]
    pub width: u32,
    #[serde(default = "default_height")]
    pub height: u32,
    /// Requested pixel format: "YUYV", "MJPG" or "RGB3". The driver may pick another size;
    /// rigd uses what it returns and says so.
    #[serde(default = "default_format")]
    pub format: PixelFormat,
    /// Manual exposure time in µs (V4L2 exposure_time_absolute is in 100 µs units).
    /// Absent: leave the camera's setting alone.
    #[serde(default)]
    pub exposure_us: Option<u32>,
    /// Manual analogue gain, in the camera's own units.
    #[serde(default)]
    pub gain: Option<i64>,
    /// Manual white balance colour temperature, kelvin.
    #[serde(default)]
    pub white_balance_k: Option<u32>,
    /// The camera's sharpening, V4L2 `sharpness` in its own units: 0 turns a UVC webcam's
    /// off on most. Its halos, made in sRGB, are the largest single bias a webcam's
    /// processing puts on an offset (docs/method.md, "What is left"). Absent: leave it.
    #[serde(default)]
    pub sharpness: Option<i64>,
    /// Capture buffers to queue.
    #[serde(default = "default_buffers")]
    pub buffers: u32,
    /// Deadline for each dequeue.
    #[serde(default = "default_frame_timeout_ms")]
    pub frame_timeout_ms: u64,
    /// The camera's output curve, "linear" or "srgb": frames are measured in linear light.
    /// Absent: the sim camera's own curve; "srgb" for v4l2 (UVC webcams encode sRGB; set
    /// "linear" for a machine-vision camera with its gamma at 1).
    #[serde(default)]
    pub response: Option<crate::pipeline::Response>,
    /// The print's ink density statistics, `{ density_rms = 0.04, corr_um = 3000 }`, as
    /// measured once on a print (docs/calibration.md): the fit then takes the print's
    /// uneven density as a prior. Absent: the sim camera's own print; none for v4l2.
    #[serde(default)]
    pub ink_prior: Option<crate::pipeline::InkPrior>,
    /// sim: the simulated camera's model (defaults when absent).
    #[serde(default)]
    pub sim: Option<SimCameraTable>,
}

fn default_width() -> u32 {
    1280
}
fn default_height() -> u32 {
    720
}
fn default_format() -> PixelFormat {
    PixelFormat::Yuyv
}
fn default_buffers() -> u32 {
    4
}
fn default_frame_timeout_ms() -> u64 {
    2_000
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Xl80Config {
    /// The log file the interferometer software writes (relative to the config file).
    pub path: PathBuf,
    pub format: Xl80Format,
    /// Unit of `.rtx` samples when the file's header names none (CARTO files do not):
    /// "mm" (default), "um"/"µm", "nm", "m", "in".
    #[serde(default = "default_rtx_unit")]
    pub rtx_unit: String,
    /// How often a growing log is polled during a job.
    #[serde(default = "default_poll_ms")]
    pub poll_ms: u64,
    /// Step alignment: a plateau is where the trace stays within this band (µm).
    #[serde(default = "default_plateau_tol_um")]
    pub plateau_tol_um: f64,
}

fn default_rtx_unit() -> String {
    "mm".to_string()
}
fn default_poll_ms() -> u64 {
    200
}
fn default_plateau_tol_um() -> f64 {
    5.0
}

/// `[pipeline]`: how the camera sees the rig (every job on this rig uses it) and the
/// processing defaults of jobs that leave a setting out. A default left out here leaves such
/// a job to the protocol's own default (for `combine` that depends on the scan's k).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PipelineConfig {
    /// Size of one camera pixel on the board, µm.
    pub scale_um_per_px: f64,
    /// Image displacement per unit of axis travel, [x, y] in image axes.
    pub axis_dir: [f64; 2],
    /// Image displacement per unit of piezo travel (absent: the axis's), for scans that
    /// move the piezo besides the axis (a 2-D grid, a list).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub piezo_dir: Option<[f64; 2]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub k: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub estimator: Option<Estimator>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub combine: Option<Combine>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub registration: Option<Registration>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub whole_frame: Option<bool>,
}

impl Default for PipelineConfig {
    fn default() -> Self {
        PipelineConfig {
            scale_um_per_px: 774.0,
            axis_dir: [-1.0, 0.0],
            piezo_dir: None,
            k: None,
            estimator: None,
            combine: None,
            registration: None,
            whole_frame: None,
        }
    }
}

/// Where the daemon listens and records: `[daemon]` in a config file, overridden by
/// `rigd --socket/--data-root`, defaulted when neither says ([`DaemonSettings::default`]).
/// `rigd` serves on these (and locks them: `ownership`); `rigd` and `rigctl hw`
/// lock the devices in `lock_dir`, so both resolve it the same way.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DaemonSettings {
    /// The Unix socket clients connect to.
    pub socket: PathBuf,
    /// Group given access to the socket (mode 0660); absent: owner only (0600).
    pub group: Option<String>,
    /// Where sessions are recorded.
    pub data_root: PathBuf,
    /// Where the serial devices' locks live, shared with `rigctl hw` (default: /run/lock
    /// when writable, else $XDG_RUNTIME_DIR, else /tmp: see `lock::lock_dir`).
    pub lock_dir: Option<PathBuf>,
    /// Clients served at once; one more is told `unavailable` and closed. Lowered to what
    /// the open-file limit leaves (`daemon::accept::RESERVED_FDS` kept for the rig).
    pub max_connections: usize,
    /// Bytes queued for one client (replies and events) before its events are dropped and
    /// its requests wait.
    pub output_queue_bytes: usize,
    /// A client whose queue stays full this long (it reads nothing) is disconnected.
    pub stalled_client_ms: u64,
    /// A connection with no subscription that sends nothing this long is closed (0: never).
    pub idle_timeout_s: u64,
    /// The memory one job may need to process (its estimate at submit), MB.
    pub max_job_memory_mb: u64,
    /// A controller's feed hold mid-job: `pause` the job (resume goes on) or `fail` it.
    pub on_feed_hold: crate::acquisition::HoldPolicy,
    /// A current calibration older than this, days, still applies, with a warning in every
    /// job's events, result and manifest and in the log.
    pub calibration_max_age_days: f64,
}

/// `[daemon] max_connections` when the config leaves it out.
pub const DEFAULT_MAX_CONNECTIONS: usize = 64;

impl Default for DaemonSettings {
    /// The socket clients look for by default ([`default_socket`]) and `./rigd-sessions`.
    fn default() -> Self {
        DaemonSettings {
            socket: default_socket(),
            group: None,
            data_root: PathBuf::from("rigd-sessions"),
            lock_dir: None,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            output_queue_bytes: 1 << 20,
            stalled_client_ms: 10_000,
            idle_timeout_s: 600,
            max_job_memory_mb: 2048,
            on_feed_hold: crate::acquisition::HoldPolicy::Pause,
            calibration_max_age_days: crate::calibration_note::DEFAULT_MAX_AGE_DAYS,
        }
    }
}

impl DaemonSettings {
    /// These settings with whatever the command line gives instead.
    pub fn overridden(self, socket: Option<PathBuf>, data_root: Option<PathBuf>) -> Self {
        DaemonSettings {
            socket: socket.unwrap_or(self.socket),
            data_root: data_root.unwrap_or(self.data_root),
            ..self
        }
    }
}

/// The socket path when neither the command line nor a config names one:
/// `$RIGD_SOCKET`, else `$XDG_RUNTIME_DIR/rigd.sock`, else `/tmp/rigd-<uid>.sock`.
pub fn default_socket() -> PathBuf {
    if let Some(p) = std::env::var_os("RIGD_SOCKET") {
        return PathBuf::from(p);
    }
    if let Some(d) = std::env::var_os("XDG_RUNTIME_DIR") {
        return PathBuf::from(d).join("rigd.sock");
    }
    let uid = nix::unistd::getuid();
    PathBuf::from(format!("/tmp/rigd-{uid}.sock"))
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoardConfig {
    /// The target board's TOML (relative to the config file).
    pub path: PathBuf,
}

impl Config {
    /// Read and check a config file. Relative paths inside it are taken relative to its
    /// directory.
    pub fn load(path: impl AsRef<Path>) -> Result<Config, ConfigError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|error| ConfigError::Read {
            path: path.to_path_buf(),
            error,
        })?;
        Config::from_toml_str(&text, path)
    }

    /// Parse config text; `origin` names it in errors and anchors relative paths.
    pub fn from_toml_str(text: &str, origin: &Path) -> Result<Config, ConfigError> {
        let mut cfg: Config = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: origin.to_path_buf(),
            message: e.to_string().trim_end().to_string(),
        })?;
        cfg.source = origin.to_path_buf();
        cfg.validate()?;
        let base = origin.parent().unwrap_or(Path::new(""));
        let anchor = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        };
        if let Some(x) = cfg.xl80.as_mut() {
            anchor(&mut x.path);
        }
        if let Some(b) = cfg.board.as_mut() {
            anchor(&mut b.path);
        }
        Ok(cfg)
    }

    /// How long the camera may take to deliver a frame ([camera] frame_timeout_ms, or its
    /// default without a [camera] section).
    pub fn frame_timeout_ms(&self) -> u64 {
        self.camera
            .as_ref()
            .map_or_else(default_frame_timeout_ms, |c| c.frame_timeout_ms)
    }

    fn invalid(&self, key: &str, message: impl Into<String>) -> ConfigError {
        ConfigError::Invalid {
            path: self.source.clone(),
            key: key.to_string(),
            message: message.into(),
        }
    }

    fn validate(&self) -> Result<(), ConfigError> {
        for (name, stage) in [("axis", &self.axis), ("piezo", &self.piezo)] {
            if let Some(s) = stage {
                self.validate_stage(name, s)?;
            }
        }
        if let Some(c) = &self.camera {
            if c.driver == CameraDriver::V4l2 && c.device.as_deref().unwrap_or("").is_empty() {
                return Err(self.invalid("camera.device", "required with driver = \"v4l2\""));
            }
            if c.width == 0 || c.height == 0 {
                return Err(self.invalid(
                    "camera.width",
                    format!("frame size {}x{} is empty", c.width, c.height),
                ));
            }
            if c.buffers == 0 {
                return Err(self.invalid("camera.buffers", "must be at least 1"));
            }
            if c.frame_timeout_ms == 0 {
                return Err(self.invalid("camera.frame_timeout_ms", "must be positive"));
            }
            if let Some(p) = &c.ink_prior {
                p.check()
                    .map_err(|e| self.invalid("camera.ink_prior", e.to_string()))?;
            }
        }
        if let Some(x) = &self.xl80 {
            if crate::xl80::length_unit_um(&x.rtx_unit).is_none() {
                return Err(self.invalid(
                    "xl80.rtx_unit",
                    format!("unknown unit {:?} (mm, um, nm, m, in)", x.rtx_unit),
                ));
            }
            if !(x.plateau_tol_um.is_finite() && x.plateau_tol_um > 0.0) {
                return Err(self.invalid("xl80.plateau_tol_um", "must be a positive number"));
            }
        }
        let p = &self.pipeline;
        self.validate_dir("pipeline.axis_dir", p.axis_dir, "axis")?;
        if let Some(d) = p.piezo_dir {
            self.validate_dir("pipeline.piezo_dir", d, "piezo")?;
        }
        if !(p.scale_um_per_px.is_finite() && p.scale_um_per_px > 0.0) {
            return Err(self.invalid("pipeline.scale_um_per_px", "must be a positive number"));
        }
        // The pipeline owns the k range (the one the protocol and the CLI use).
        if let Some(k) = p.k.filter(|k| !crate::pipeline::K_RANGE.contains(k)) {
            let r = crate::pipeline::K_RANGE;
            let msg = format!("must be {}..={}, got {k}", r.start(), r.end());
            return Err(self.invalid("pipeline.k", msg));
        }
        Ok(())
    }

    /// An image direction: finite and non-zero.
    fn validate_dir(&self, key: &str, [dx, dy]: [f64; 2], stage: &str) -> Result<(), ConfigError> {
        if dx.is_finite() && dy.is_finite() && dx.hypot(dy) != 0.0 {
            return Ok(());
        }
        Err(self.invalid(
            key,
            format!(
                "must be a finite, non-zero [x, y] (image displacement per unit of {stage} \
                 travel), got [{dx}, {dy}]"
            ),
        ))
    }

    fn validate_stage(&self, name: &str, s: &StageConfig) -> Result<(), ConfigError> {
        // Numbers in messages print short: 1e308, not 309 digits.
        use crate::text::short_um as um;
        let key = |k: &str| format!("{name}.{k}");
        let needs_port = matches!(s.driver, StageDriver::Grbl | StageDriver::Gcs);
        if needs_port && s.port.as_deref().unwrap_or("").is_empty() {
            return Err(self.invalid(&key("port"), "required with a serial driver"));
        }
        if s.baud == 0 {
            return Err(self.invalid(&key("baud"), "must be positive"));
        }
        for (k, v) in [
            ("soft_min_um", s.soft_min_um),
            ("soft_max_um", s.soft_max_um),
            ("max_step_um", s.max_step_um),
            ("feed_um_s", s.feed_um_s),
            ("um_per_unit", s.um_per_unit),
        ] {
            if !v.is_finite() {
                return Err(self.invalid(&key(k), format!("{v} is not a finite number")));
            }
        }
        if s.soft_min_um >= s.soft_max_um {
            return Err(self.invalid(
                &key("soft_max_um"),
                format!(
                    "soft_max_um ({}) must be above soft_min_um ({})",
                    um(s.soft_max_um),
                    um(s.soft_min_um)
                ),
            ));
        }
        if s.max_step_um <= 0.0 {
            return Err(self.invalid(&key("max_step_um"), "must be positive"));
        }
        self.validate_default_start(name, s)?;
        if s.feed_um_s <= 0.0 {
            return Err(self.invalid(&key("feed_um_s"), "must be positive"));
        }
        if s.um_per_unit <= 0.0 {
            return Err(self.invalid(&key("um_per_unit"), "must be positive"));
        }
        let max_hz = crate::hw::grbl::MAX_POLL_HZ;
        if !(s.status_poll_hz > 0.0 && s.status_poll_hz <= max_hz) {
            return Err(self.invalid(
                &key("status_poll_hz"),
                format!(
                    "must be above 0 and at most {max_hz} (GRBL's most), not {}",
                    s.status_poll_hz
                ),
            ));
        }
        if s.driver == StageDriver::Gcs
            && (s.gcs_axis.is_empty() || s.gcs_axis.contains(char::is_whitespace))
        {
            return Err(self.invalid(
                &key("gcs_axis"),
                format!("{:?} is not a GCS axis identifier", s.gcs_axis),
            ));
        }
        self.validate_waits(name, s)
    }

    /// `[axis] default_start_um`: only the axis has one, inside its soft limits.
    fn validate_default_start(&self, name: &str, s: &StageConfig) -> Result<(), ConfigError> {
        use crate::text::short_um as um;
        let key = |k: &str| format!("{name}.{k}");
        let Some(v) = s.default_start_um else {
            return Ok(());
        };
        if name != "axis" {
            return Err(self.invalid(
                &key("default_start_um"),
                "only [axis] has a default scan start (piezo scans start at its soft_min_um)",
            ));
        }
        if !(v.is_finite() && (s.soft_min_um..=s.soft_max_um).contains(&v)) {
            return Err(self.invalid(
                &key("default_start_um"),
                format!(
                    "{} is outside the soft limits [{}, {}]",
                    um(v),
                    um(s.soft_min_um),
                    um(s.soft_max_um)
                ),
            ));
        }
        Ok(())
    }

    /// The controller deadlines are positive; the settle time is bounded.
    fn validate_waits(&self, name: &str, s: &StageConfig) -> Result<(), ConfigError> {
        let key = |k: &str| format!("{name}.{k}");
        for (k, v) in [
            ("reply_timeout_ms", s.reply_timeout_ms),
            ("move_timeout_ms", s.move_timeout_ms),
            ("open_timeout_ms", s.open_timeout_ms),
            ("home_timeout_ms", s.home_timeout_ms),
        ] {
            if v == 0 {
                return Err(self.invalid(&key(k), "must be positive"));
            }
        }
        let max_settle = crate::acquisition::plan::MAX_SETTLE_MS;
        if s.settle_ms > max_settle {
            return Err(self.invalid(
                &key("settle_ms"),
                format!("{} ms is over the {max_settle} ms bound", s.settle_ms),
            ));
        }
        Ok(())
    }

    fn missing(&self, section: &'static str, purpose: &str) -> ConfigError {
        ConfigError::Missing {
            path: self.source.clone(),
            section,
            purpose: purpose.to_string(),
        }
    }

    /// The `[axis]` section, or an error naming the file and what needed it.
    pub fn axis(&self, purpose: &str) -> Result<&StageConfig, ConfigError> {
        self.axis
            .as_ref()
            .ok_or_else(|| self.missing("axis", purpose))
    }
    pub fn piezo(&self, purpose: &str) -> Result<&StageConfig, ConfigError> {
        self.piezo
            .as_ref()
            .ok_or_else(|| self.missing("piezo", purpose))
    }
    pub fn camera(&self, purpose: &str) -> Result<&CameraConfig, ConfigError> {
        self.camera
            .as_ref()
            .ok_or_else(|| self.missing("camera", purpose))
    }
    pub fn xl80(&self, purpose: &str) -> Result<&Xl80Config, ConfigError> {
        self.xl80
            .as_ref()
            .ok_or_else(|| self.missing("xl80", purpose))
    }
}

impl Xl80Config {
    /// µm per RTX sample unit (validated at load).
    pub fn rtx_um_per_unit(&self) -> f64 {
        crate::xl80::length_unit_um(&self.rtx_unit).unwrap_or(1000.0)
    }

    /// Read the whole configured log.
    pub fn read(&self) -> Result<crate::xl80::Xl80Log, crate::xl80::Xl80Error> {
        crate::xl80::read_with(&self.path, self.format, self.rtx_um_per_unit())
    }

    /// A follower for the configured log (during a job).
    pub fn follower(&self) -> crate::xl80::Follower {
        crate::xl80::Follower::new(&self.path, self.format).with_rtx_unit_um(self.rtx_um_per_unit())
    }
}

impl StageConfig {
    /// Soft travel limits and maximum step, as the drivers check them.
    pub fn limits(&self) -> TravelLimits {
        TravelLimits {
            min_um: self.soft_min_um,
            max_um: self.soft_max_um,
            max_step_um: self.max_step_um,
        }
    }

    /// The GRBL driver's options from this section.
    pub fn grbl_options(&self) -> GrblOptions {
        GrblOptions {
            port: self.port.clone().unwrap_or_default(),
            baud: self.baud,
            feed_um_s: self.feed_um_s,
            banner_timeout_ms: self.open_timeout_ms,
            reply_timeout_ms: self.reply_timeout_ms,
            home_timeout_ms: self.home_timeout_ms,
            on_alarm: self.on_alarm,
            home_on_connect: self.home_on_connect,
            status_poll_hz: self.status_poll_hz,
            limits: self.limits(),
        }
    }

    /// The PI GCS driver's options from this section.
    pub fn gcs_options(&self) -> GcsOptions {
        GcsOptions {
            port: self.port.clone().unwrap_or_default(),
            baud: self.baud,
            axis: self.gcs_axis.clone(),
            um_per_unit: self.um_per_unit,
            reply_timeout_ms: self.reply_timeout_ms,
            servo_on_connect: self.servo_on_connect,
            home_um: self.home_um,
            home_reference: self.home_reference,
            move_timeout_ms: self.move_timeout_ms,
            home_timeout_ms: self.home_timeout_ms,
            limits: self.limits(),
        }
    }

    /// Where a scan on this stage starts when a job gives no `start_um`.
    pub fn scan_start_um(&self) -> f64 {
        self.default_start_um
            .unwrap_or(self.soft_min_um.max(0.0).min(self.soft_max_um))
    }

    /// Deadline for a move to finish and settle.
    pub fn move_timeout(&self) -> Duration {
        Duration::from_millis(self.move_timeout_ms)
    }

    /// The settle wait after a move.
    pub fn settle(&self) -> Duration {
        Duration::from_millis(self.settle_ms)
    }
}

impl CameraConfig {
    /// The V4L2 driver's options from this section.
    pub fn v4l2_options(&self) -> V4l2Options {
        V4l2Options {
            device: self.device.clone().unwrap_or_default(),
            width: self.width,
            height: self.height,
            format: self.format,
            exposure_us: self.exposure_us,
            gain: self.gain,
            white_balance_k: self.white_balance_k,
            sharpness: self.sharpness,
            buffers: self.buffers,
            frame_timeout: Duration::from_millis(self.frame_timeout_ms),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pipeline_defaults_are_only_the_keys_the_file_sets() {
        let origin = Path::new("/etc/rigd/rigd.toml");
        let cfg = Config::from_toml_str(
            "[pipeline]\nk = 4\ncombine = \"splat\"\nwhole_frame = false\n",
            origin,
        )
        .unwrap();
        let p = &cfg.pipeline;
        assert_eq!(
            (p.k, p.estimator, p.combine, p.registration, p.whole_frame),
            (Some(4), None, Some(Combine::Splat), None, Some(false))
        );
        let none = Config::from_toml_str("[pipeline]\nscale_um_per_px = 500.0\n", origin).unwrap();
        assert_eq!(
            none.pipeline,
            PipelineConfig {
                scale_um_per_px: 500.0,
                ..PipelineConfig::default()
            }
        );
        assert_eq!(none.frame_timeout_ms(), 2000, "the [camera] default");
        let cam = Config::from_toml_str(
            "[camera]\ndriver = \"sim\"\nframe_timeout_ms = 750\n",
            origin,
        )
        .unwrap();
        assert_eq!(cam.frame_timeout_ms(), 750);
    }

    #[test]
    fn daemon_settings_come_from_the_command_line_then_the_file_then_defaults() {
        let origin = Path::new("/etc/rigd/rigd.toml");
        let file = Config::from_toml_str("[daemon]\nsocket = \"/run/x.sock\"\n", origin).unwrap();
        assert_eq!(file.daemon.socket, PathBuf::from("/run/x.sock"));
        assert_eq!(file.daemon.data_root, PathBuf::from("rigd-sessions"));
        let cli = file
            .daemon
            .clone()
            .overridden(None, Some(PathBuf::from("/data")));
        assert_eq!(cli.socket, PathBuf::from("/run/x.sock"));
        assert_eq!(cli.data_root, PathBuf::from("/data"));
        let bare = Config::from_toml_str("", origin).unwrap();
        assert_eq!(bare.daemon, DaemonSettings::default());
        assert_eq!(bare.daemon.socket, default_socket());
    }
}
