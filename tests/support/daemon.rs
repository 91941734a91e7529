//! The daemon as the daemon tests drive it: in-process on a temporary socket and data root,
//! or the `rigd` binary as a child process; a client that submits jobs and follows their
//! events to the end; the session a job wrote; a fast GRBL emulator for hardware-mode rigs.

use rigd::acquisition::JobSpec;
use rigd::cli::client::Client;
use rigd::config::Config;
use rigd::config::DaemonSettings;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::daemon::server::Background;
use rigd::rig::from_config;
use rigd::rig::Rig;
use rigd::rig::SimSettings;
use rigd::session::{Session, SessionState};
use rigd::sim::grbl::{GrblSim, GrblSimOptions};
use rigd::sim::motion::{Axis, AxisParams};
use rigd::sim::CameraModel;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// A config rig with a sim axis and a small fast sim camera (48x32 frames every 2 ms).
pub const SIM_RIG_SMALL: &str = r#"
[axis]
driver = "sim"
soft_min_um = 0.0
soft_max_um = 100000.0
max_step_um = 100000.0
[camera]
driver = "sim"
[camera.sim]
width = 48
height = 32
supersample = 2
frame_period_ms = 2.0
exposure_ms = 1.0
"#;

/// `text` parsed as if read from `dir/rig.toml`.
pub fn config(dir: &Path, text: &str) -> Config {
    Config::from_toml_str(text, &dir.join("rig.toml")).unwrap()
}

/// The rig a config `text` (read from `dir/rig.toml`) builds.
pub fn rig_from_toml(dir: &Path, text: &str) -> Rig {
    from_config(&config(dir, text)).unwrap()
}

/// A small fast sim camera for `rigd --sim` rigs: 48x32 frames every millisecond.
pub fn fast_camera() -> CameraModel {
    CameraModel {
        width: 48,
        height: 32,
        supersample: 2,
        frame_period_ms: 1.0,
        exposure_ms: 0.5,
        ..CameraModel::default()
    }
}

/// The sim rig most daemon tests use: 300x200 frames every 2 ms with the small board
/// (written into `dir`), everything else the simulator's defaults.
pub fn small_board_sim(dir: &Path) -> SimSettings {
    let board = dir.join("small.toml");
    std::fs::write(&board, super::SMALL_BOARD).unwrap();
    SimSettings {
        camera: CameraModel {
            width: 300,
            height: 200,
            supersample: 2,
            frame_period_ms: 2.0,
            exposure_ms: 1.0,
            ..CameraModel::default()
        },
        board_file: Some(board),
        ..SimSettings::default()
    }
}

/// A daemon running in this process on `dir/rigd.sock`, its data root `dir/data`.
pub struct Daemon {
    pub bg: Background,
    pub data: PathBuf,
    _dir: tempfile::TempDir,
}

impl Daemon {
    /// Serve `rig` from a new temporary folder.
    pub fn start(rig: Rig) -> Daemon {
        Daemon::start_in(rig, tempfile::tempdir().unwrap())
    }

    /// Serve `rig` with its socket and data root in `dir` (kept until the daemon drops).
    pub fn start_in(rig: Rig, dir: tempfile::TempDir) -> Daemon {
        Daemon::start_with(rig, dir, |_| {})
    }

    /// As [`Daemon::start_in`], with settings changed by `f`.
    pub fn start_with(
        rig: Rig,
        dir: tempfile::TempDir,
        f: impl FnOnce(&mut DaemonSettings),
    ) -> Daemon {
        let data = dir.path().join("data");
        let mut settings = DaemonSettings {
            socket: dir.path().join("rigd.sock"),
            group: None,
            data_root: data.clone(),
            ..DaemonSettings::default()
        };
        f(&mut settings);
        Daemon {
            bg: Background::start(settings, rig).unwrap(),
            data,
            _dir: dir,
        }
    }

    /// A new connection, not subscribed.
    pub fn client(&self) -> Client {
        Client::connect(&self.bg.socket).unwrap()
    }

    /// A new connection subscribed to every job's events.
    pub fn subscribed(&self) -> Client {
        let mut c = self.client();
        subscribe(&mut c);
        c
    }

    /// The session a job's events name, opened from this daemon's data root.
    pub fn session(&self, events: &[EventBody]) -> Session {
        session_of(&self.data, events)
    }
}

/// Subscribe `c` to every job's events.
pub fn subscribe(c: &mut Client) {
    c.request(&Request::Subscribe { job_id: None }).unwrap();
}

/// Submit `job`; its id.
pub fn submit(c: &mut Client, job: JobSpec) -> u64 {
    job_id(&c.request(&Request::Submit { job }).unwrap())
}

/// The `job_id` of a submit or replay reply.
pub fn job_id(reply: &serde_json::Value) -> u64 {
    reply["job_id"]
        .as_u64()
        .unwrap_or_else(|| panic!("no job id in {reply}"))
}

/// Events of job `id` until its terminal one, which is last (the client is subscribed).
pub fn events_until_end(c: &mut Client, id: u64) -> Vec<EventBody> {
    let mut v = Vec::new();
    loop {
        let e = c.next_event().unwrap();
        if e.job_id != id {
            continue;
        }
        let end = e.body.is_terminal();
        v.push(e.body);
        if end {
            return v;
        }
    }
}

/// The terminal event of job `id`, skipping everything before it.
pub fn end_of(c: &mut Client, id: u64) -> EventBody {
    events_until_end(c, id).pop().unwrap()
}

/// Send a job-starting request (submit or replay) and follow the job to its end: its id
/// and its events, the terminal one last.
pub fn run_request(c: &mut Client, req: &Request) -> (u64, Vec<EventBody>) {
    let id = job_id(&c.request(req).unwrap());
    (id, events_until_end(c, id))
}

/// Every session `list` gives, page after page (newest first).
pub fn list_all_sessions(c: &mut Client) -> Vec<serde_json::Value> {
    let mut all = Vec::new();
    let mut before = None;
    loop {
        let r = c
            .request(&Request::List {
                limit: Some(rigd::daemon::protocol::LIST_MAX),
                before,
            })
            .unwrap();
        all.extend(r["sessions"].as_array().unwrap().iter().cloned());
        match r["next_before"].as_u64() {
            Some(b) => before = Some(b),
            None => return all,
        }
    }
}

/// Submit `job` and follow it to its end: its id and its events, the terminal one last.
pub fn run_job(c: &mut Client, job: JobSpec) -> (u64, Vec<EventBody>) {
    run_request(c, &Request::Submit { job })
}

/// The job ended `finished`.
pub fn assert_finished(events: &[EventBody]) {
    assert!(
        matches!(events.last(), Some(EventBody::Finished { .. })),
        "{events:?}"
    );
}

/// The session named by a job's `started` event.
pub fn session_name(events: &[EventBody]) -> String {
    events
        .iter()
        .find_map(|e| match e {
            EventBody::Started { session, .. } => Some(session.clone()),
            _ => None,
        })
        .expect("a started event")
}

/// The session a job's events name, opened from the data root `data`.
pub fn session_of(data: &Path, events: &[EventBody]) -> Session {
    Session::open(&data.join(session_name(events))).unwrap()
}

/// `(index, commanded_um)` of every step a job's events report.
pub fn reported_steps(events: &[EventBody]) -> Vec<(u32, f64)> {
    events
        .iter()
        .filter_map(|e| match e {
            EventBody::Step {
                index,
                commanded_um,
                ..
            } => Some((*index, *commanded_um)),
            _ => None,
        })
        .collect()
}

/// A `rigd --sim` child process; killed if a test fails before it does.
pub struct RigdProcess(pub Option<Child>);

impl RigdProcess {
    /// Start `rigd --sim` on `socket` and `data`, and wait until it answers.
    pub fn spawn_sim(socket: &Path, data: &Path) -> RigdProcess {
        let args = [
            "--sim".as_ref(),
            "--socket".as_ref(),
            socket.as_os_str(),
            "--data-root".as_ref(),
            data.as_os_str(),
        ];
        RigdProcess::spawn(&args, socket)
    }

    /// Start `rigd ARGS`, and wait until it answers on `socket`.
    pub fn spawn(args: &[&std::ffi::OsStr], socket: &Path) -> RigdProcess {
        let child = Command::new(env!("CARGO_BIN_EXE_rigd"))
            .args(args)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let child = RigdProcess(Some(child));
        let t = Instant::now();
        while Client::connect(socket).is_err() {
            assert!(t.elapsed() < Duration::from_secs(20), "rigd did not start");
            std::thread::sleep(Duration::from_millis(20));
        }
        child
    }

    /// The child, taken out: dropping `self` then kills nothing.
    pub fn take(&mut self) -> Child {
        self.0.take().expect("rigd is running")
    }

    /// `kill -9` the daemon and reap it.
    pub fn kill_9(&mut self) {
        let mut dead = self.take();
        dead.kill().unwrap(); // SIGKILL
        dead.wait().unwrap();
    }
}

impl Drop for RigdProcess {
    fn drop(&mut self) {
        if let Some(c) = self.0.as_mut() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// The GRBL emulator on a pseudo-terminal serving a fast exact axis (50 mm/s, 2 m/s²,
/// no positioning error); the axis to see where it really is.
pub fn fast_grbl() -> (Arc<Axis>, GrblSim) {
    let axis = Arc::new(Axis::new(AxisParams {
        max_speed_um_s: 50_000.0,
        accel_um_s2: 2_000_000.0,
        position_error_rms_um: 0.0,
        ..AxisParams::default()
    }));
    let grbl = GrblSim::spawn(Arc::clone(&axis), GrblSimOptions::default(), None).unwrap();
    (axis, grbl)
}

/// A capture-only job (no processing) of `steps` frames `step_um` apart from the rig's
/// default start, settling `settle_ms` before each frame.
pub fn capture_job(step_um: f64, steps: u32, settle_ms: u64) -> JobSpec {
    JobSpec {
        step_um: Some(step_um),
        steps: Some(steps),
        settle_ms,
        process: false,
        ..JobSpec::default()
    }
}

/// Every frame `s`'s steps.csv lists decodes whole, at `size` (width, height).
pub fn assert_frames_decode(s: &Session, size: (u32, u32)) {
    for r in &s.steps {
        let img = image::open(s.frame_path(r.index))
            .unwrap_or_else(|e| panic!("frame {} of {}: {e}", r.index, s.dir.display()));
        assert_eq!((img.width(), img.height()), size, "frame {}", r.index);
    }
}

/// Run `job` to its end on a small sim rig (64x40 frames of the small board, an
/// interferometer) and copy its finished session out of the daemon's data root into `dir`.
pub fn record_small(dir: &Path, job: JobSpec) -> Session {
    let board = dir.join("small.toml");
    std::fs::write(&board, super::SMALL_BOARD).unwrap();
    let settings = SimSettings {
        camera: CameraModel {
            width: 64,
            height: 40,
            supersample: 2,
            frame_period_ms: 2.0,
            exposure_ms: 1.0,
            ..CameraModel::default()
        },
        board_file: Some(board),
        ..SimSettings::default()
    };
    let d = Daemon::start_in(
        rigd::rig::simulated(&settings).unwrap(),
        tempfile::tempdir().unwrap(),
    );
    let mut c = d.subscribed();
    let (_, ev) = run_job(&mut c, job);
    let s = d.session(&ev);
    assert_eq!(s.manifest.state, SessionState::Finished);
    let to = dir.join(&s.manifest.name);
    copy_dir(&s.dir, &to);
    Session::open(&to).unwrap()
}

/// A copy of the tree at `from` (files and folders) at `to`.
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}
