//! The `rigd` binary: `kill -9` mid-job then restart, and a clean stop on SIGTERM.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{assert_frames_decode, capture_job, submit, subscribe, RigdProcess};
use rigd::acquisition::JobSpec;
use rigd::cli::client::Client;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::session::{Session, SessionState};
use std::path::PathBuf;

/// Submit a long capture-only job and wait until `n` steps are reported; returns the job id,
/// its session and the indices reported captured.
fn run_until_steps(c: &mut Client, n: usize) -> (u64, String, Vec<u32>) {
    subscribe(c);
    let job = capture_job(50.0, 400, 0);
    let id = submit(c, job);
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
    assert_frames_decode(s, s.manifest.rig.frame_size);
}

#[test]
fn kill_9_mid_job_leaves_a_readable_session_marked_incomplete_on_restart() {
    let dir = tempfile::tempdir().unwrap();
    let (socket, data): (PathBuf, PathBuf) = (dir.path().join("s.sock"), dir.path().join("data"));
    let mut child = RigdProcess::spawn_sim(&socket, &data);
    let mut c = Client::connect(&socket).unwrap();
    let (id, name, reported) = run_until_steps(&mut c, 3);
    child.kill_9();
    // Read right after the crash: every reported frame is there, state still `running`.
    let s = Session::open(&data.join(&name)).unwrap();
    assert_eq!(s.manifest.state, SessionState::Running);
    check_frames(&s, &reported);
    // A restarted daemon marks it incomplete and numbers new jobs after it.
    let _child = RigdProcess::spawn_sim(&socket, &data);
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
    let new_id = submit(&mut c, job);
    assert!(new_id > id);
}

#[test]
fn sigterm_finishes_the_step_closes_the_session_and_removes_the_socket() {
    let dir = tempfile::tempdir().unwrap();
    let (socket, data) = (dir.path().join("s.sock"), dir.path().join("data"));
    let mut reaper = RigdProcess::spawn_sim(&socket, &data);
    let mut c = Client::connect(&socket).unwrap();
    let (_, name, reported) = run_until_steps(&mut c, 2);
    let child = reaper.take();
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
