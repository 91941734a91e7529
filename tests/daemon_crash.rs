//! The `rigd` binary: `kill -9` mid-job then restart, and a clean stop on SIGTERM.

use rigd::cli::client::Client;
use rigd::daemon::protocol::{EventBody, JobSpec, Request};
use rigd::daemon::session::{Session, SessionState};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Kills the daemon if a test fails before it does.
struct Reaper(Option<Child>);

impl Drop for Reaper {
    fn drop(&mut self) {
        if let Some(c) = self.0.as_mut() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

fn spawn_rigd(socket: &Path, data: &Path) -> Reaper {
    let child = Command::new(env!("CARGO_BIN_EXE_rigd"))
        .args(["--sim", "--socket"])
        .arg(socket)
        .arg("--data-root")
        .arg(data)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let child = Reaper(Some(child));
    let t = Instant::now();
    while Client::connect(socket).is_err() {
        assert!(t.elapsed() < Duration::from_secs(20), "rigd did not start");
        std::thread::sleep(Duration::from_millis(20));
    }
    child
}

/// Submit a long capture-only job and wait until `n` steps are reported; returns the job id,
/// its session and the indices reported captured.
fn run_until_steps(c: &mut Client, n: usize) -> (u64, String, Vec<u32>) {
    c.request(&Request::Subscribe { job_id: None }).unwrap();
    let job = JobSpec {
        step_um: Some(50.0),
        steps: Some(400),
        settle_ms: 0,
        process: false,
        ..JobSpec::default()
    };
    let id = c.request(&Request::Submit { job }).unwrap()["job_id"]
        .as_u64()
        .unwrap();
    let (mut session, mut steps) = (String::new(), Vec::new());
    while steps.len() < n {
        let e = c.next_event().unwrap();
        match e.body {
            EventBody::Started { session: s, .. } => session = s,
            EventBody::Step { index, .. } => steps.push(index),
            other => assert!(!other.is_terminal(), "{other:?}"),
        }
    }
    (id, session, steps)
}

fn check_frames(s: &Session, reported: &[u32]) {
    let on_disk: Vec<u32> = s.steps.iter().map(|r| r.index).collect();
    for i in reported {
        assert!(
            on_disk.contains(i),
            "frame {i} was reported but is not in steps.csv"
        );
    }
    for r in &s.steps {
        let img =
            image::open(s.frame_path(r.index)).unwrap_or_else(|e| panic!("frame {}: {e}", r.index));
        assert_eq!(img.width(), s.manifest.rig.frame_size.0);
    }
}

#[test]
fn kill_9_mid_job_leaves_a_readable_session_marked_incomplete_on_restart() {
    let dir = tempfile::tempdir().unwrap();
    let (socket, data): (PathBuf, PathBuf) = (dir.path().join("s.sock"), dir.path().join("data"));
    let mut child = spawn_rigd(&socket, &data);
    let mut c = Client::connect(&socket).unwrap();
    let (id, name, reported) = run_until_steps(&mut c, 3);
    let mut dead = child.0.take().unwrap();
    dead.kill().unwrap(); // SIGKILL
    dead.wait().unwrap();
    // Read right after the crash: every reported frame is there, state still `running`.
    let s = Session::open(&data.join(&name)).unwrap();
    assert_eq!(s.manifest.state, SessionState::Running);
    check_frames(&s, &reported);
    // A restarted daemon marks it incomplete and numbers new jobs after it.
    let _child = spawn_rigd(&socket, &data);
    let s = Session::open(&data.join(&name)).unwrap();
    assert_eq!(s.manifest.state, SessionState::Incomplete);
    assert_eq!(s.manifest.frames_captured as usize, s.steps.len());
    check_frames(&s, &reported);
    let mut c = Client::connect(&socket).unwrap();
    let st = c.request(&Request::Status { job_id: Some(id) }).unwrap();
    assert_eq!(st["session"], name.as_str());
    let job = JobSpec {
        steps: Some(1),
        process: false,
        ..JobSpec::default()
    };
    let new_id = c.request(&Request::Submit { job }).unwrap()["job_id"]
        .as_u64()
        .unwrap();
    assert!(new_id > id);
}

#[test]
fn sigterm_finishes_the_step_closes_the_session_and_removes_the_socket() {
    let dir = tempfile::tempdir().unwrap();
    let (socket, data) = (dir.path().join("s.sock"), dir.path().join("data"));
    let mut reaper = spawn_rigd(&socket, &data);
    let mut c = Client::connect(&socket).unwrap();
    let (_, name, reported) = run_until_steps(&mut c, 2);
    let child = reaper.0.take().unwrap();
    // SAFETY: signalling our own child process.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success(), "{:?}", out.status);
    assert!(!socket.exists(), "the socket is removed on a clean stop");
    let s = Session::open(&data.join(&name)).unwrap();
    assert_eq!(s.manifest.state, SessionState::Cancelled);
    assert!(s
        .manifest
        .reason
        .as_deref()
        .unwrap()
        .contains("shutting down"));
    assert!(s.steps.len() < 400);
    check_frames(&s, &reported);
}
