//! The daemon over its real Unix socket, in-process, on a small fast simulated rig:
//! queueing, cancel, faults, disconnecting clients, many clients, replay, and a short soak.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::daemon::{
    assert_finished, assert_frames_decode, capture_job, events_until_end, fast_camera, job_id,
    list_all_sessions, submit, subscribe, Daemon,
};
use rigd::acquisition::{JobSpec, Processing};
use rigd::cli::client::Client;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::rig::{simulated, Fault, SimSettings};
use rigd::session::SessionState;
use serde_json::Value;

fn start(faults: Vec<Fault>) -> Daemon {
    let mut rig = simulated(&SimSettings {
        camera: fast_camera(),
        faults,
        ..SimSettings::default()
    })
    .unwrap();
    // A short grab deadline (`rigd --sim --grab-timeout-ms`): the camera-timeout case
    // waits 0.5 s, not the sim's default 5 s.
    rig.info.grab_timeout_ms = 500;
    Daemon::start(rig)
}

fn scan(steps: u32, settle_ms: u64) -> JobSpec {
    capture_job(50.0, steps, settle_ms)
}

#[test]
fn a_job_runs_its_steps_in_order_and_records_every_frame() {
    let d = start(vec![]);
    let mut c = d.subscribed();
    let id = submit(&mut c, scan(5, 0));
    let ev = events_until_end(&mut c, id);
    assert!(matches!(
        ev[0],
        EventBody::Accepted {
            total_frames: 5,
            ..
        }
    ));
    assert_finished(&ev);
    let steps: Vec<(u32, f64, f64)> = ev
        .iter()
        .filter_map(|e| match e {
            EventBody::Step {
                index,
                commanded_um,
                interferometer_um,
                ..
            } => Some((*index, *commanded_um, interferometer_um.unwrap())),
            _ => None,
        })
        .collect();
    assert_eq!(
        steps.iter().map(|s| s.0).collect::<Vec<_>>(),
        vec![0, 1, 2, 3, 4]
    );
    for (i, cmd, ifm) in &steps {
        assert_eq!(*cmd, 1000.0 + 50.0 * *i as f64);
        // The axis ends within its random positioning error (2 µm RMS) of the target.
        assert!((ifm - cmd).abs() < 12.0, "interferometer {ifm} vs {cmd}");
    }
    let s = d.session(&ev);
    assert_eq!(s.manifest.state, SessionState::Finished);
    assert_eq!(s.steps.len(), 5);
    assert_frames_decode(&s, (48, 32));
    let text = std::fs::read_to_string(s.dir.join("steps.csv")).unwrap();
    assert!(text.starts_with("index,position_um,"), "{text}");
    let st = c.request(&Request::Status { job_id: Some(id) }).unwrap();
    assert_eq!(
        (st["state"].as_str(), st["frames_done"].as_u64()),
        (Some("finished"), Some(5))
    );
}

#[test]
fn jobs_queue_behind_the_running_one_and_cancel_stops_them() {
    let d = start(vec![]);
    let mut c = d.subscribed();
    let long = submit(&mut c, scan(200, 20));
    let queued = c.request(&Request::Submit { job: scan(3, 0) }).unwrap();
    assert_eq!(queued["queue_position"].as_u64(), Some(1));
    let queued = queued["job_id"].as_u64().unwrap();
    let st = c.request(&Request::Status { job_id: None }).unwrap();
    assert_eq!(st["queued"], serde_json::json!([queued]));
    // Cancel the queued job: it never starts.
    let r = c.request(&Request::Cancel { job_id: queued }).unwrap();
    assert_eq!(r["state"], "cancelled");
    // Let the long job take a few steps, then cancel it.
    let mut seen = 0;
    while seen < 3 {
        let e = c.next_event().unwrap();
        if e.job_id == long && matches!(e.body, EventBody::Step { .. }) {
            seen += 1;
        }
    }
    assert_eq!(
        c.request(&Request::Cancel { job_id: long }).unwrap()["state"],
        "cancelling"
    );
    let ev = events_until_end(&mut c, long);
    assert!(matches!(
        ev.last(),
        Some(EventBody::Cancelled {
            session: Some(_),
            ..
        })
    ));
    let st = c.request(&Request::Status { job_id: Some(long) }).unwrap();
    let done = st["frames_done"].as_u64().unwrap();
    assert!((3..200).contains(&done), "{done}");
    let list = c
        .request(&Request::List {
            limit: None,
            before: None,
        })
        .unwrap();
    let sessions = list["sessions"].as_array().unwrap();
    assert_eq!(sessions.len(), 1, "the cancelled queued job has no session");
    assert_eq!(sessions[0]["state"], "cancelled");
    assert_eq!(sessions[0]["frames_captured"].as_u64(), Some(done));
    // Cancelling again names the problem.
    let e = c.request(&Request::Cancel { job_id: long }).unwrap_err();
    assert!(e.to_string().contains("already"), "{e}");
}

#[test]
fn each_injected_fault_fails_the_job_with_its_reason_and_keeps_the_frames() {
    for (fault, want, kept) in [
        (Fault::Alarm(4), "alarm", 3),
        (Fault::SerialLoss(3), "port gone", 2),
        (Fault::CameraTimeout(5), "no reply within 500 ms", 4),
    ] {
        let d = start(vec![fault]);
        let mut c = d.subscribed();
        let id = submit(&mut c, scan(10, 0));
        let ev = events_until_end(&mut c, id);
        let Some(EventBody::Failed { reason, .. }) = ev.last() else {
            panic!("{fault:?}: {ev:?}")
        };
        assert!(reason.contains(want), "{fault:?}: {reason}");
        let s = d.session(&ev);
        assert_eq!(s.manifest.state, SessionState::Failed);
        assert_eq!(s.steps.len(), kept, "{fault:?}");
        assert!(s.manifest.reason.as_deref().unwrap().contains(want));
        // The daemon keeps serving.
        c.request(&Request::Hello {}).unwrap();
    }
}

#[test]
fn a_client_that_disconnects_does_not_affect_its_job() {
    let d = start(vec![]);
    let id = {
        let mut c = d.subscribed();
        submit(&mut c, scan(8, 5))
    };
    let mut c = d.client();
    let r = c.request(&Request::Subscribe { job_id: Some(id) }).unwrap();
    let ev = if r["status"]["state"] == "finished" {
        vec![]
    } else {
        events_until_end(&mut c, id)
    };
    assert!(ev.is_empty() || matches!(ev.last(), Some(EventBody::Finished { .. })));
    let st = c.request(&Request::Status { job_id: Some(id) }).unwrap();
    assert_eq!(
        (st["state"].as_str(), st["frames_done"].as_u64()),
        (Some("finished"), Some(8))
    );
}

#[test]
fn many_clients_at_once_all_get_their_jobs_done() {
    let d = start(vec![]);
    let socket = d.bg.socket.clone();
    let threads: Vec<_> = (0..16)
        .map(|i| {
            let socket = socket.clone();
            std::thread::spawn(move || {
                let mut c = Client::connect(&socket).unwrap();
                subscribe(&mut c);
                let id = submit(&mut c, scan(1 + i % 3, 0));
                // Interleave other requests while the queue drains.
                c.request(&Request::List {
                    limit: None,
                    before: None,
                })
                .unwrap();
                c.request(&Request::Status { job_id: None }).unwrap();
                let ev = events_until_end(&mut c, id);
                (id, ev.last().cloned(), 1 + i % 3)
            })
        })
        .collect();
    let mut ids = Vec::new();
    for t in threads {
        let (id, last, _) = t.join().unwrap();
        assert!(matches!(last, Some(EventBody::Finished { .. })), "{last:?}");
        ids.push(id);
    }
    ids.sort();
    ids.dedup();
    assert_eq!(ids.len(), 16);
    let mut c = d.client();
    let list = c
        .request(&Request::List {
            limit: None,
            before: None,
        })
        .unwrap();
    let frames: u64 = list["sessions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["frames_captured"].as_u64().unwrap())
        .sum();
    assert_eq!(frames, (0..16).map(|i| 1 + i % 3).sum::<u64>());
}

#[test]
fn replay_feeds_the_recorded_frames_and_positions_through_the_job_path() {
    let d = start(vec![]);
    let mut c = d.subscribed();
    let live = submit(
        &mut c,
        JobSpec {
            process: true,
            ..scan(4, 0)
        },
    );
    let ev = events_until_end(&mut c, live);
    let live_s = d.session(&ev);
    let r = c
        .request(&Request::Replay {
            session: live_s.manifest.name.clone(),
            processing: Processing::default(),
        })
        .unwrap();
    let rid = job_id(&r);
    let ev = events_until_end(&mut c, rid);
    assert_finished(&ev);
    let rs = d.session(&ev);
    assert_eq!(
        rs.manifest.replay_of.as_deref(),
        Some(live_s.manifest.name.as_str())
    );
    assert_eq!(rs.manifest.rig.mode, rigd::rig::RigMode::Replay);
    assert_eq!(rs.steps.len(), 4);
    // No frame copied: the replay's frames are the recorded session's.
    assert!(!rs.dir.join("frames").exists(), "the replay copied frames");
    let live_name = live_s.manifest.name.clone();
    assert_eq!(rs.manifest.frames_from.as_deref(), Some(live_name.as_str()));
    for (a, b) in live_s.steps.iter().zip(&rs.steps) {
        assert_eq!(
            (a.position_um, a.axis_um, a.interferometer_um, a.sequence),
            (b.position_um, b.axis_um, b.interferometer_um, b.sequence)
        );
        assert_eq!(rs.frame_path(b.index), live_s.frame_path(a.index));
        assert_eq!(
            rs.read_frame(b.index).unwrap(),
            live_s.read_frame(a.index).unwrap()
        );
    }
    // Same frames, same positions, same pipeline: the same result.
    let a = c.request(&Request::Result { job_id: live }).unwrap();
    let b = c.request(&Request::Result { job_id: rid }).unwrap();
    assert_eq!(a["result"]["runs"], b["result"]["runs"]);
    // A replay of the replay reads the recorded session's frames too, and so does
    // `rigctl process` on the replay's session.
    let r2 = c
        .request(&Request::Replay {
            session: rs.manifest.name.clone(),
            processing: Processing::default(),
        })
        .unwrap();
    let ev = events_until_end(&mut c, job_id(&r2));
    assert_finished(&ev);
    let rs2 = d.session(&ev);
    assert_eq!(
        rs2.manifest.replay_of.as_deref(),
        Some(rs.manifest.name.as_str())
    );
    assert_eq!(
        rs2.manifest.frames_from.as_deref(),
        Some(live_name.as_str())
    );
    assert!(!rs2.dir.join("frames").exists());
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(["process", "--json"])
        .arg(&rs2.dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let offline: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(offline["runs"], a["result"]["runs"]);
    // An unknown session or a path outside the data root is refused.
    for bad in ["nope", "../etc", ".hidden"] {
        let e = c
            .request(&Request::Replay {
                session: bad.into(),
                processing: Processing::default(),
            })
            .unwrap_err();
        assert!(
            e.to_string().contains(bad) || e.to_string().contains("session"),
            "{e}"
        );
    }
}

/// A short soak: 200 one-frame jobs, each on its own connection, on a `rigd` child whose
/// open files and RSS are read from /proc (its own: this test process runs other tests
/// beside it). The long version: `SOAK_JOBS=3000 cargo test --test suite
/// daemon_jobs::soak -- --nocapture`.
#[test]
fn soak_short_jobs_leak_neither_files_nor_memory() {
    use crate::support::adversary::{capture_job, follow, open_fds, rss_kb, Spawn};
    let n: usize = std::env::var("SOAK_JOBS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(200);
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(env!("CARGO_BIN_EXE_rigd"), dir.path()).start();
    let run = |count: usize| {
        for _ in 0..count {
            let mut c = d.client();
            c.request(r#"{"kind": "subscribe"}"#);
            let id = c.request(&capture_job(1, 0, "soak"))["result"]["job_id"]
                .as_u64()
                .expect("a job id");
            let ev = follow(&mut c, id);
            assert_eq!(ev.last().unwrap()["event"], "finished", "{ev:?}");
        }
    };
    run(30); // warm up: allocator pools, runtime threads, the job table's first growth
    let (fd0, rss0) = (open_fds(d.pid()), rss_kb(d.pid()).0);
    let t = std::time::Instant::now();
    run(n);
    let (fd1, rss1) = (open_fds(d.pid()), rss_kb(d.pid()).0);
    eprintln!(
        "soak: {n} jobs in {:.1} s; open fds {fd0} -> {fd1}; RSS {rss0} -> {rss1} kB",
        t.elapsed().as_secs_f64()
    );
    assert!(fd1 <= fd0 + 2, "open files grew: {fd0} -> {fd1}");
    assert!(rss1 < rss0 + 8 * 1024, "memory grew: {rss0} -> {rss1} kB");
    let mut c = Client::connect(&d.socket).unwrap();
    assert_eq!(list_all_sessions(&mut c).len(), n + 30);
}

#[test]
fn hello_names_the_protocol_and_the_rig() {
    let d = start(vec![]);
    let r: Value = d.client().request(&Request::Hello {}).unwrap();
    assert_eq!(r["protocol"], 1);
    assert_eq!(r["rig"]["mode"], "sim");
    assert_eq!(r["rig"]["frame_size"], serde_json::json!([48, 32]));
}
