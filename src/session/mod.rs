//! Session folders: one per job under the data root (docs/sessions.md).
//!
//! Crash safety: every file is written under a temporary name, synced and renamed into
//! place, so a reader sees either the old or the new version, never half a file. A frame's
//! PNG and its `steps.csv` row are in place before the job reports the step, and the
//! manifest's state is updated last. After a crash the manifest still says `running`; the
//! next daemon start marks such sessions `incomplete`.
//!
//! The exceptions are `steps.csv` and `interferometer.csv`, which grow by a row a frame and
//! by hundreds of samples a second: they are appended to and fsynced (rewriting them whole
//! per frame would be quadratic in a job's length). A frame's PNG is in place before its
//! `steps.csv` row, and its samples before either. A crash can leave an unterminated last
//! line, which readers skip; every row up to the last reported frame is complete.

use crate::acquisition::outcome::EndDetail;
use crate::acquisition::plan::Plan;
use crate::acquisition::study::JobResult;
use crate::acquisition::JobSpec;
use crate::atomic_file::{self, AtomicWriteError};
use crate::bounds;
use crate::text::wire_name;
pub mod frame_png;

use crate::acquisition::rig::RigInfo;
use crate::hw::devices::StageMachine;
use crate::hw::{LogSample, LogSource};
use crate::nofollow::{self, Access};
use crate::results_csv;
use crate::versions::PROTOCOL_VERSION;
use image::RgbImage;
use serde::{Deserialize, Serialize};
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

pub const FORMAT: &str = "rigd-session/1";
pub const MANIFEST: &str = "manifest.json";
pub const STEPS: &str = "steps.csv";
pub const INTERFEROMETER: &str = "interferometer.csv";
pub const RESULT: &str = "result.json";
/// Columns of `interferometer.csv`.
pub const INTERFEROMETER_HEADER: &str = "t_unix_s,position_um,sample\n";

pub use crate::acquisition::processor::Image16;
pub use crate::timestamps::unix_s;

/// Columns of `steps.csv`, the `rigctl process` contract (`index,position_um`) first; the
/// piezo's last (empty unless the plan moves it besides the axis), so readers of the
/// earlier columns keep working.
pub const STEPS_HEADER: &str = "index,position_um,run,case,repeat,axis_um,interferometer_um,\
t_unix_s,sequence,move_ms,settle_ms,grab_ms,piezo_commanded_um,piezo_um\n";

#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error("session {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("session {path}: {message}")]
    Format { path: String, message: String },
    #[error("session {path}: disk full ({source})")]
    DiskFull {
        path: String,
        source: std::io::Error,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> SessionError + '_ {
    move |source| {
        let path = path.display().to_string();
        match source.raw_os_error() {
            Some(libc::ENOSPC | libc::EDQUOT) => SessionError::DiskFull { path, source },
            _ => SessionError::Io { path, source },
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum SessionState {
    Running,
    Finished,
    Failed,
    Cancelled,
    /// The daemon died while the job ran: everything on disk is readable, the rest is lost.
    Incomplete,
}

/// A resumed session's link to the one it resumes (`rigd::daemon::resuming`): its frames
/// before `first_index` are that session's (and, if it was itself resumed, its original's).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct ResumedFrom {
    /// The session resumed (its name under the data root).
    pub session: String,
    /// The plan index of the first frame the new session took (the first missing one).
    pub first_index: u32,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Versions {
    pub rigd: String,
    pub protocol: u32,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub name: String,
    pub job_id: u64,
    pub state: SessionState,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// The reason's fields (kind, device, file, where the stage was left).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub detail: Option<EndDetail>,
    pub created_unix_s: f64,
    pub updated_unix_s: f64,
    pub job: JobSpec,
    pub plan: Plan,
    /// The session this one replays, if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub replay_of: Option<String>,
    /// The interrupted session this one resumes, if any; never written into that one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub resumed_from: Option<ResumedFrom>,
    /// A replay's frames are not copied: the session (a sibling folder under the data root)
    /// whose `frames/` holds them, the first recorded one of a chain of replays. Absent: the
    /// frames are in this session's own `frames/` (replays written before rigd 0.2 too).
    pub frames_from: Option<String>,
    pub rig: RigInfo,
    /// The interferometer log the session's `interferometer.csv` was read from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub interferometer: Option<LogSource>,
    pub versions: Versions,
    pub frames_captured: u32,
    /// The calibration the job applied, or why none (absent from sessions recorded before
    /// the daemon kept calibrations).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<crate::calibration_note::CalibrationNote>,
}

/// One row of `steps.csv`: the `rigctl process` contract (`index,position_um`) first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepRow {
    pub index: u32,
    /// Commanded position.
    pub position_um: f64,
    pub run: u32,
    pub case: String,
    pub repeat: u32,
    pub axis_um: f64,
    pub interferometer_um: Option<f64>,
    /// Exposure time of the frame.
    pub t_unix_s: f64,
    pub sequence: u64,
    pub move_ms: f64,
    pub settle_ms: f64,
    pub grab_ms: f64,
    /// A plan that moves the piezo besides the axis: its commanded position and where it
    /// settled (absent from sessions recorded before 2-D plans).
    #[serde(default)]
    pub piezo_commanded_um: Option<f64>,
    #[serde(default)]
    pub piezo_um: Option<f64>,
}

impl Manifest {
    /// Its times in range ([`bounds`]): a manifest is a file, and may have been edited.
    pub fn check(&self) -> Result<(), String> {
        bounds::in_range(
            "created_unix_s",
            self.created_unix_s,
            0.0,
            bounds::MAX_UNIX_S,
        )?;
        bounds::in_range(
            "updated_unix_s",
            self.updated_unix_s,
            0.0,
            bounds::MAX_UNIX_S,
        )?;
        bounds::one_component("name", &self.name)?;
        let (w, h) = self.rig.frame_size;
        bounds::frame_size(w, h).map_err(|e| format!("rig.frame_size {e}"))?;
        bounds::in_range("rig.scale_um_per_px", self.rig.scale_um_per_px, 1e-6, 1e6)?;
        if let Some(m) = &self.rig.axis_machine {
            bounds::in_range("rig.axis_machine.motor_step_um", m.motor_step_um, 1e-6, 1e6)?;
            bounds::in_range("rig.axis_machine.max_rate_um_s", m.max_rate_um_s, 1e-6, 1e9)?;
            bounds::in_range("rig.axis_machine.accel_um_s2", m.accel_um_s2, 1e-6, 1e12)?;
        }
        Ok(())
    }
}

impl StepRow {
    /// Its numbers in range ([`bounds`]), each named in the error.
    pub fn check(&self) -> Result<(), String> {
        use bounds::{in_range, MAX_PHASE_MS as MS, MAX_POSITION_UM as UM};
        in_range("position_um", self.position_um, -UM, UM)?;
        in_range("axis_um", self.axis_um, -UM, UM)?;
        for (what, v) in [
            ("interferometer_um", self.interferometer_um),
            ("piezo_commanded_um", self.piezo_commanded_um),
            ("piezo_um", self.piezo_um),
        ] {
            v.map(|v| in_range(what, v, -UM, UM)).transpose()?;
        }
        in_range("t_unix_s", self.t_unix_s, 0.0, bounds::MAX_UNIX_S)?;
        in_range("move_ms", self.move_ms, 0.0, MS)?;
        in_range("settle_ms", self.settle_ms, 0.0, MS)?;
        in_range("grab_ms", self.grab_ms, 0.0, MS)?;
        Ok(())
    }

    /// The position this frame registers by without an interferometer: the commanded one,
    /// or where a stepper axis really went when its motor step is coarser than the command
    /// (`StageMachine::reached_um`, `machine` being the session's `rig.axis_machine`).
    pub fn commanded_registration_um(&self, machine: Option<&StageMachine>) -> f64 {
        machine.map_or(self.position_um, |m| {
            m.reached_um(self.position_um, self.axis_um)
        })
    }
}

impl From<AtomicWriteError> for SessionError {
    fn from(e: AtomicWriteError) -> SessionError {
        io(&e.path)(e.source)
    }
}

/// Write `bytes` to `path` atomically: temporary file, fsync, rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), SessionError> {
    Ok(atomic_file::write(path, bytes)?)
}

fn sync_dir(dir: &Path) -> Result<(), SessionError> {
    Ok(atomic_file::sync_dir(dir)?)
}

/// File name of frame `index` under `frames/`.
pub fn frame_name(index: u32) -> String {
    format!("{index:06}.png")
}

/// What a replay's session records of the session it replays: its name, and the session
/// whose `frames/` holds the frames (a replay's frames are referenced, never copied).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReplayOf {
    pub name: String,
    pub frames_from: String,
}

impl ReplayOf {
    /// A replay of `s`: its frames are where `s` reads them from.
    pub fn of(s: &Session) -> ReplayOf {
        let m = &s.manifest;
        ReplayOf {
            name: m.name.clone(),
            frames_from: m.frames_from.clone().unwrap_or_else(|| m.name.clone()),
        }
    }
}

/// Writes one session as a job runs.
pub struct SessionWriter {
    dir: PathBuf,
    manifest: Manifest,
    /// `steps.csv`, open for appending.
    steps: fs::File,
    /// `interferometer.csv`, open for appending once the job has a log.
    log: Option<fs::File>,
}

impl SessionWriter {
    /// Create `<data_root>/<name>` with its manifest in state `running`; `links`: the
    /// session it replays, the session it resumes.
    pub fn create(
        data_root: &Path,
        job_id: u64,
        job: &JobSpec,
        plan: &Plan,
        rig: &RigInfo,
        (replay_of, resumed_from): (Option<ReplayOf>, Option<ResumedFrom>),
    ) -> Result<SessionWriter, SessionError> {
        fs::create_dir_all(data_root).map_err(io(data_root))?;
        let now = SystemTime::now();
        let secs = unix_s(now) as u64;
        let base = format!("{}-job{job_id}", utc_stamp(secs));
        let mut name = base.clone();
        let mut n = 1;
        let dir = loop {
            let d = data_root.join(&name);
            match fs::create_dir(&d) {
                Ok(()) => break d,
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    n += 1;
                    name = format!("{base}-{n}");
                }
                Err(e) => return Err(io(&d)(e)),
            }
        };
        // A replay's frames stay in the session they were recorded in.
        if replay_of.is_none() {
            fs::create_dir(dir.join("frames")).map_err(io(&dir))?;
        }
        let (replay_of, frames_from) = match replay_of {
            Some(r) => (Some(r.name), Some(r.frames_from)),
            None => (None, None),
        };
        let manifest = Manifest {
            format: FORMAT.into(),
            name,
            job_id,
            state: SessionState::Running,
            reason: None,
            detail: None,
            created_unix_s: unix_s(now),
            updated_unix_s: unix_s(now),
            job: job.clone(),
            plan: plan.clone(),
            replay_of,
            resumed_from,
            frames_from,
            rig: rig.clone(),
            interferometer: None,
            versions: Versions {
                rigd: env!("CARGO_PKG_VERSION").into(),
                protocol: PROTOCOL_VERSION,
            },
            frames_captured: 0,
            calibration: None,
        };
        let steps_path = dir.join(STEPS);
        write_atomic(&steps_path, STEPS_HEADER.as_bytes())?;
        let steps =
            nofollow::open_in(&dir, Path::new(STEPS), Access::Append).map_err(io(&steps_path))?;
        let mut w = SessionWriter {
            dir,
            manifest,
            steps,
            log: None,
        };
        w.write_manifest()?;
        sync_dir(data_root)?;
        Ok(w)
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }
    pub fn name(&self) -> &str {
        &self.manifest.name
    }

    /// Record a captured frame: PNG (with its metadata: [`frame_png`]), then its steps.csv
    /// row. When this returns, the frame is on disk and may be reported captured. A replay
    /// writes the row only: its frame is already on disk, in the session it replays
    /// (`frames_from`).
    pub fn record(&mut self, row: StepRow, image: &RgbImage) -> Result<(), SessionError> {
        if self.manifest.frames_from.is_none() {
            self.write_frame(&row, image)?;
        }
        self.append_step(&row)?;
        self.manifest.frames_captured += 1;
        Ok(())
    }

    fn write_frame(&mut self, row: &StepRow, image: &RgbImage) -> Result<(), SessionError> {
        let path = self.dir.join("frames").join(frame_name(row.index));
        // The frame carries its own scale, position and time (pHYs and tEXt chunks).
        let scale = self.manifest.rig.scale_um_per_px;
        let text = frame_png::text_chunks(&self.manifest.name, row, scale);
        let png = frame_png::encode(image, scale, text).map_err(|e| SessionError::Format {
            path: path.display().to_string(),
            message: format!("PNG encoding: {e}"),
        })?;
        write_atomic(&path, &png)
    }

    /// Name the calibration the job applies (or why none) in the manifest.
    pub fn note_calibration(
        &mut self,
        note: crate::calibration_note::CalibrationNote,
    ) -> Result<(), SessionError> {
        self.manifest.calibration = Some(note);
        self.write_manifest()
    }

    /// The job has an interferometer log: record its source in the manifest and start
    /// `interferometer.csv` (header only).
    pub fn begin_interferometer(&mut self, source: LogSource) -> Result<(), SessionError> {
        let path = self.dir.join(INTERFEROMETER);
        write_atomic(&path, INTERFEROMETER_HEADER.as_bytes())?;
        sync_dir(&self.dir)?;
        self.log = Some(
            nofollow::open_in(&self.dir, Path::new(INTERFEROMETER), Access::Append)
                .map_err(io(&path))?,
        );
        self.manifest.interferometer = Some(source);
        self.write_manifest()
    }

    /// Update the log's source facts (written with the manifest's next write, at the latest
    /// when the session is closed).
    pub fn note_interferometer(&mut self, source: LogSource) {
        self.manifest.interferometer = Some(source);
    }

    /// Append interferometer samples and fsync them. Call before recording the frame they
    /// cover, so a reported frame's samples are on disk.
    pub fn append_interferometer(&mut self, samples: &[LogSample]) -> Result<(), SessionError> {
        let (Some(f), false) = (self.log.as_mut(), samples.is_empty()) else {
            return Ok(());
        };
        let mut text = String::with_capacity(samples.len() * 32);
        for s in samples {
            // `{}` prints the shortest text that reads back to the same f64.
            text.push_str(&format!("{},{},{}\n", s.t_unix_s, s.position_um, s.sample));
        }
        let path = self.dir.join(INTERFEROMETER);
        f.write_all(text.as_bytes()).map_err(io(&path))?;
        f.sync_data().map_err(io(&path))
    }

    /// Append one `steps.csv` row and fsync it.
    fn append_step(&mut self, row: &StepRow) -> Result<(), SessionError> {
        let mut w = csv::WriterBuilder::new()
            .has_headers(false)
            .from_writer(Vec::with_capacity(160));
        w.serialize(row).map_err(|e| self.format_err(e))?;
        let bytes = w.into_inner().map_err(|e| self.format_err(e))?;
        let path = self.dir.join(STEPS);
        self.steps.write_all(&bytes).map_err(io(&path))?;
        self.steps.sync_data().map_err(io(&path))
    }

    fn format_err(&self, e: impl std::fmt::Display) -> SessionError {
        SessionError::Format {
            path: self.dir.display().to_string(),
            message: e.to_string(),
        }
    }

    /// Write the result, its flat table (`results.csv`) and its images (before the final
    /// state).
    pub fn write_result(
        &mut self,
        result: &JobResult,
        images: &[(String, Image16)],
    ) -> Result<(), SessionError> {
        if !images.is_empty() {
            let dir = self.dir.join("images");
            nofollow::create_dir(&dir).map_err(io(&dir))?;
            for (name, img) in images {
                let path = dir.join(format!("{name}.png"));
                let mut png = Vec::new();
                image::DynamicImage::ImageLuma16(img.clone())
                    .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
                    .map_err(|e| self.format_err(e))?;
                write_atomic(&path, &png)?;
            }
        }
        // The job's registration names the positions (`commanded`, `interferometer`) the
        // pipeline knows only as `positions`.
        let registration = self.manifest.job.registration.map(|r| wire_name(&r));
        results_csv::write(&self.dir, &result.runs, registration.as_deref())?;
        let bytes = serde_json::to_vec_pretty(result).map_err(|e| self.format_err(e))?;
        write_atomic(&self.dir.join(RESULT), &bytes)
    }

    /// Close the session with its final state: the manifest is written last.
    pub fn close(
        mut self,
        state: SessionState,
        reason: Option<String>,
        detail: Option<EndDetail>,
    ) -> Result<(), SessionError> {
        self.manifest.state = state;
        self.manifest.reason = reason;
        self.manifest.detail = detail;
        self.write_manifest()?;
        sync_dir(&self.dir)
    }

    fn write_manifest(&mut self) -> Result<(), SessionError> {
        self.manifest.updated_unix_s = unix_s(SystemTime::now());
        let bytes = serde_json::to_vec_pretty(&self.manifest).map_err(|e| self.format_err(e))?;
        write_atomic(&self.dir.join(MANIFEST), &bytes)
    }
}

/// A session read back from disk.
#[derive(Debug, Clone)]
pub struct Session {
    pub dir: PathBuf,
    pub manifest: Manifest,
    pub steps: Vec<StepRow>,
}

impl Session {
    /// Read the session in `dir`. Nothing is read through a symlink: not `dir` itself, nor
    /// any file in it ([`nofollow`]).
    pub fn open(dir: &Path) -> Result<Session, SessionError> {
        let manifest = Session::read_manifest(dir)?;
        let spath = dir.join(STEPS);
        let text =
            nofollow::read_in_max(dir, STEPS, bounds::MAX_STEPS_BYTES).map_err(io(&spath))?;
        // A crash mid-append can leave half a row: every complete row ends in a newline.
        let complete = match text.iter().rposition(|&b| b == b'\n') {
            Some(i) => &text[..=i],
            None => &text[..0],
        };
        let mut rd = csv::Reader::from_reader(complete);
        let mut steps = Vec::new();
        for (i, row) in rd.deserialize::<StepRow>().enumerate() {
            let bad = |e: String| SessionError::Format {
                path: spath.display().to_string(),
                message: format!("row {}: {e}", i + 1),
            };
            let row = row.map_err(|e| bad(e.to_string()))?;
            row.check().map_err(bad)?;
            steps.push(row);
        }
        Ok(Session {
            dir: dir.to_path_buf(),
            manifest,
            steps,
        })
    }

    /// The manifest of the session in `dir` alone (bounded, its numbers checked), read as
    /// [`Session::open`] reads it.
    pub fn read_manifest(dir: &Path) -> Result<Manifest, SessionError> {
        let mpath = dir.join(MANIFEST);
        let text =
            nofollow::read_in_max(dir, MANIFEST, bounds::MAX_DOCUMENT_BYTES).map_err(io(&mpath))?;
        let format = |message: String| SessionError::Format {
            path: mpath.display().to_string(),
            message,
        };
        let manifest: Manifest =
            serde_json::from_slice(&text).map_err(|e| format(bounds::cut(&e.to_string(), 300)))?;
        manifest.check().map_err(format)?;
        Ok(manifest)
    }

    /// Where frame `index` is: the folder to read it from (this session's, or for a replay
    /// the sibling session named by `frames_from`) and its path below it, for
    /// [`nofollow::read_in`]. A `frames_from` that is not a plain folder name is refused.
    pub fn frame_file(&self, index: u32) -> Result<(PathBuf, PathBuf), SessionError> {
        let rel = Path::new("frames").join(frame_name(index));
        let Some(from) = &self.manifest.frames_from else {
            return Ok((self.dir.clone(), rel));
        };
        let plain = matches!(
            Path::new(from).components().collect::<Vec<_>>()[..],
            [std::path::Component::Normal(_)]
        );
        let parent = self
            .dir
            .parent()
            .filter(|_| plain && !from.starts_with('.'));
        match parent {
            Some(root) => Ok((root.join(from), rel)),
            None => Err(SessionError::Format {
                path: self.dir.join(MANIFEST).display().to_string(),
                message: format!("frames_from `{from}` is not a session name"),
            }),
        }
    }

    /// The path of frame `index` (for people and tests; read it with [`Session::read_frame`]).
    pub fn frame_path(&self, index: u32) -> PathBuf {
        match self.frame_file(index) {
            Ok((dir, rel)) => dir.join(rel),
            Err(_) => self.dir.join("frames").join(frame_name(index)),
        }
    }

    /// The bytes of frame `index`'s PNG, read without following a symlink ([`nofollow`]),
    /// at most [`bounds::MAX_FRAME_BYTES`].
    pub fn read_frame(&self, index: u32) -> Result<Vec<u8>, SessionError> {
        let (dir, rel) = self.frame_file(index)?;
        nofollow::read_in_max(&dir, &rel, bounds::MAX_FRAME_BYTES).map_err(io(&dir.join(&rel)))
    }

    /// The interferometer samples recorded (`interferometer.csv`), oldest first; empty when
    /// the session has none. An unterminated last line (cut by a crash) is skipped.
    pub fn interferometer_samples(&self) -> Result<Vec<LogSample>, SessionError> {
        let path = self.dir.join(INTERFEROMETER);
        let text = match nofollow::read_in_max(&self.dir, INTERFEROMETER, bounds::MAX_LOG_BYTES) {
            Ok(t) => String::from_utf8_lossy(&t).into_owned(),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(io(&path)(e)),
        };
        let complete = match text.rfind('\n') {
            Some(i) => &text[..i],
            None => "",
        };
        let bad = |line: usize, message: String| SessionError::Format {
            path: path.display().to_string(),
            message: format!("line {line}: {message}"),
        };
        let mut out = Vec::new();
        for (i, line) in complete.lines().enumerate().skip(1) {
            let f: Vec<&str> = line.split(',').collect();
            if f.len() < 2 {
                return Err(bad(i + 1, format!("{line:?} is not t_unix_s,position_um")));
            }
            let num = |s: &str, what: &str| {
                s.trim()
                    .parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| bad(i + 1, format!("{what} {s:?} is not a number")))
            };
            out.push(LogSample {
                t_unix_s: num(f[0], "t_unix_s")?,
                position_um: num(f[1], "position_um")?,
                sample: f.get(2).and_then(|s| s.trim().parse().ok()).unwrap_or(0),
            });
        }
        Ok(out)
    }

    /// The stored result, if the job got that far.
    pub fn result(&self) -> Option<serde_json::Value> {
        let bytes = nofollow::read_in_max(&self.dir, RESULT, bounds::MAX_STEPS_BYTES).ok()?;
        serde_json::from_slice(&bytes).ok()
    }
}

/// Sessions under `data_root`, oldest first (by name: names start with a UTC stamp).
pub fn list(data_root: &Path) -> Vec<Session> {
    let (sessions, skipped) = scan(data_root);
    for (path, reason) in skipped {
        tracing::debug!(path = %path.display(), %reason, "not a session");
    }
    sessions
}

/// Sessions under `data_root`, oldest first, and the entries skipped that looked like one
/// (a symlink, a session that cannot be read), each with why. Only real folders are
/// entered: a symlink is never followed out of the data root.
pub fn scan(data_root: &Path) -> (Vec<Session>, Vec<(PathBuf, String)>) {
    let Ok(rd) = fs::read_dir(data_root) else {
        return (Vec::new(), Vec::new());
    };
    let mut v = Vec::new();
    let mut skipped = Vec::new();
    for e in rd.flatten() {
        let path = e.path();
        // DirEntry::file_type does not follow a symlink.
        match e.file_type() {
            Ok(t) if t.is_symlink() => skipped.push((
                path,
                "a symbolic link: not followed out of the data root".into(),
            )),
            Ok(t) if t.is_dir() => match Session::open(&path) {
                Ok(s) => v.push(s),
                // A folder without a manifest is not a session (nothing to say).
                Err(SessionError::Io { source, .. })
                    if source.kind() == std::io::ErrorKind::NotFound => {}
                Err(err) => skipped.push((path, err.to_string())),
            },
            _ => {}
        }
    }
    v.sort_by(|a, b| a.manifest.name.cmp(&b.manifest.name));
    (v, skipped)
}

/// At daemon start: sessions left `running` by a daemon that died (or that could not write
/// its final manifest, e.g. on a full disk) are marked `incomplete`, after their leftover
/// temporaries (`.NAME.tmp` of a write cut short) are removed. A session that cannot be
/// marked now (the disk is still full) is left `running` with a warning, to be marked at
/// a later start: it must not keep the daemon from starting. Entries that are skipped (a
/// symlink, an unreadable session) are logged with their path and why. Returns the highest
/// job id seen, so new ids do not collide with recorded ones, and the sessions marked.
pub fn recover(data_root: &Path) -> Result<(u64, Vec<String>), SessionError> {
    let mut max_id = 0;
    let mut marked = Vec::new();
    let (sessions, skipped) = scan(data_root);
    for (path, reason) in skipped {
        tracing::warn!(path = %path.display(), %reason, "skipped at recovery");
    }
    for s in sessions {
        max_id = max_id.max(s.manifest.job_id);
        if s.manifest.state == SessionState::Running {
            remove_leftovers(&s.dir);
            let mut m = s.manifest.clone();
            m.state = SessionState::Incomplete;
            m.reason = Some("the daemon stopped while the job ran".into());
            m.frames_captured = s.steps.len() as u32;
            m.updated_unix_s = unix_s(SystemTime::now());
            let bytes = serde_json::to_vec_pretty(&m).map_err(|e| SessionError::Format {
                path: s.dir.display().to_string(),
                message: e.to_string(),
            })?;
            match write_atomic(&s.dir.join(MANIFEST), &bytes) {
                Ok(()) => marked.push(m.name),
                Err(e) => tracing::warn!(session = %m.name, "cannot mark it incomplete yet: {e}"),
            }
        }
    }
    Ok((max_id, marked))
}

/// Mark the session in `dir`, if still `running`, failed with `reason` (a job whose thread
/// panicked: nothing else will close it).
pub fn mark_failed(dir: &Path, reason: &str) -> Result<(), SessionError> {
    let s = Session::open(dir)?;
    let mut m = s.manifest;
    if m.state != SessionState::Running {
        return Ok(());
    }
    m.state = SessionState::Failed;
    m.reason = Some(reason.to_string());
    m.frames_captured = s.steps.len() as u32;
    m.updated_unix_s = unix_s(SystemTime::now());
    let bytes = serde_json::to_vec_pretty(&m).map_err(|e| SessionError::Format {
        path: dir.display().to_string(),
        message: e.to_string(),
    })?;
    write_atomic(&dir.join(MANIFEST), &bytes)
}

/// Remove the temporaries (`.NAME.tmp`) a write cut short left in a session, its `frames/`
/// and `images/`: regular files only, found without following a symlink (a symlinked
/// folder or temporary is logged and left alone).
fn remove_leftovers(session: &Path) {
    for sub in ["", "frames", "images"] {
        let dir = session.join(sub);
        match fs::symlink_metadata(&dir) {
            Ok(m) if m.file_type().is_dir() => {}
            Ok(m) if m.file_type().is_symlink() => {
                tracing::warn!(path = %dir.display(), "skipped at recovery: a symbolic link: not followed");
                continue;
            }
            _ => continue,
        }
        let Ok(rd) = fs::read_dir(&dir) else { continue };
        for e in rd.flatten() {
            let name = e.file_name();
            let name = name.to_string_lossy();
            if !(name.starts_with('.') && name.ends_with(".tmp")) {
                continue;
            }
            let path = e.path();
            match e.file_type() {
                Ok(t) if t.is_file() => match fs::remove_file(&path) {
                    Ok(()) => {
                        tracing::info!(path = %path.display(), "removed a leftover temporary")
                    }
                    Err(err) => {
                        tracing::warn!(path = %path.display(), error = %err, "cannot remove a leftover temporary")
                    }
                },
                _ => {
                    tracing::warn!(path = %path.display(), "skipped at recovery: not a regular file")
                }
            }
        }
    }
}

/// `YYYYMMDDTHHMMSSZ` for seconds since the epoch (UTC).
pub fn utc_stamp(secs: u64) -> String {
    let stamp = time::macros::format_description!("[year][month][day]T[hour][minute][second]Z");
    let t = time::OffsetDateTime::from_unix_timestamp(secs.min(i64::MAX as u64) as i64)
        .unwrap_or(time::OffsetDateTime::UNIX_EPOCH);
    // Cannot fail: every component is in an OffsetDateTime and a String takes any length.
    t.format(stamp).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row() -> StepRow {
        StepRow {
            index: 0,
            position_um: 10.0,
            run: 0,
            case: "c".into(),
            repeat: 0,
            axis_um: 10.0,
            interferometer_um: Some(10.0),
            t_unix_s: 1_795_000_000.0,
            sequence: 1,
            move_ms: 1.0,
            settle_ms: 1.0,
            grab_ms: 1.0,
            piezo_commanded_um: None,
            piezo_um: None,
        }
    }

    /// ±0, denormals, the extremes, NaN, the infinities and ordinary numbers.
    fn extreme() -> impl proptest::strategy::Strategy<Value = f64> {
        use proptest::prelude::*;
        prop_oneof![
            Just(0.0),
            Just(-0.0),
            Just(5e-324),
            Just(-2.2e-308),
            Just(1e308),
            Just(-1e308),
            Just(f64::NAN),
            Just(f64::INFINITY),
            Just(f64::NEG_INFINITY),
            any::<f64>(),
            -1e4f64..1e4,
        ]
    }

    proptest::proptest! {
        /// Every number of a steps.csv row: accepted only in its range, refused naming it.
        #[test]
        fn step_row_numbers_are_range_checked(field in 0usize..7, v in extreme()) {
            let mut r = row();
            let (name, lo, hi) = match field {
                0 => { r.position_um = v; ("position_um", -1e9, 1e9) }
                1 => { r.axis_um = v; ("axis_um", -1e9, 1e9) }
                2 => { r.interferometer_um = Some(v); ("interferometer_um", -1e9, 1e9) }
                3 => { r.t_unix_s = v; ("t_unix_s", 0.0, 1e10) }
                4 => { r.move_ms = v; ("move_ms", 0.0, 1e9) }
                5 => { r.settle_ms = v; ("settle_ms", 0.0, 1e9) }
                _ => { r.piezo_um = Some(v); ("piezo_um", -1e9, 1e9) }
            };
            match r.check() {
                Ok(()) => proptest::prop_assert!((lo..=hi).contains(&v)),
                Err(e) => {
                    proptest::prop_assert!(!(lo..=hi).contains(&v));
                    proptest::prop_assert!(e.starts_with(name), "{}", e);
                }
            }
        }
    }

    #[test]
    fn utc_stamps_match_known_dates() {
        assert_eq!(utc_stamp(0), "19700101T000000Z");
        assert_eq!(utc_stamp(1_795_000_000), "20261118T110640Z");
    }
}
