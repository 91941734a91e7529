//! `resume_session` on the sim rig, over the real socket: a job that failed mid-way (the
//! sim camera's stream stalls at a grab, `--fault camera-timeout@N`) is resumed as a new job
//! that takes exactly the missing frames of the same plan, linked to the original, whose
//! data stays untouched; the resumed session's result gives every run from all its frames
//! (the original's for the run split across the two, and the runs wholly in it), as an
//! uninterrupted job's does. Sessions that cannot be resumed are refused naming why; a frame
//! without its row, or cut short, counts as missing.

#![cfg(feature = "sim")]

use crate::support::daemon::*;
use rigd::acquisition::JobSpec;
use rigd::cli::client::Client;
use rigd::daemon::protocol::{EventBody, Request};
use rigd::rig::{simulated, Fault, SimSettings};
use rigd::session::{ResumedFrom, Session, SessionState};
use rigd::sim::CameraModel;
use serde_json::Value;
use std::path::Path;

/// 3 repeats of 4 frames a quarter pixel apart: runs 0..3, frames 0..12.
const FRAMES: u32 = 12;
/// The stream stalls at this grab: frames 0..6 are kept, run 1 is split (4, 5 | 6, 7).
const STALL_AT_GRAB: u32 = 7;

fn start(dir: &Path, faults: Vec<Fault>) -> Daemon {
    let board = dir.join("small.toml");
    std::fs::write(&board, crate::support::SMALL_BOARD).unwrap();
    let mut rig = simulated(&SimSettings {
        camera: CameraModel {
            width: 300,
            height: 200,
            supersample: 2,
            frame_period_ms: 2.0,
            exposure_ms: 1.0,
            ..CameraModel::default()
        },
        board_file: Some(board),
        faults,
        ..SimSettings::default()
    })
    .unwrap();
    rig.info.grab_timeout_ms = 500;
    Daemon::start_in(rig, tempfile::tempdir().unwrap())
}

fn job() -> JobSpec {
    JobSpec {
        step_um: Some(193.5),
        steps: Some(4),
        repeats: 3,
        k: Some(4),
        settle_ms: 0,
        ..JobSpec::default()
    }
}

/// `resume_session`: its reply, or the error as rigctl prints it (`rigd: <code>: <message>`).
fn resume(c: &mut Client, session: &str) -> Result<Value, String> {
    c.request(&Request::ResumeSession {
        session: session.into(),
    })
    .map_err(|e| e.to_string())
}

/// Each run's (run, frames, result.frames, the positions its steps list).
fn runs(result: &Value) -> Vec<(u64, u64, u64, Vec<f64>)> {
    result["runs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            let res = &r["result"];
            assert!(res.is_object(), "run without a result: {r}");
            let at = res["steps"]
                .as_array()
                .unwrap()
                .iter()
                .map(|s| s["position_um"].as_f64().unwrap())
                .collect();
            (
                r["run"].as_u64().unwrap(),
                r["frames"].as_u64().unwrap(),
                res["frames"].as_u64().unwrap(),
                at,
            )
        })
        .collect()
}

/// Each run's targets' offsets (µm).
fn offsets(result: &Value) -> Vec<Vec<(f64, f64)>> {
    result["runs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            r["result"]["objects"]
                .as_array()
                .unwrap()
                .iter()
                .map(|o| {
                    let v = &o["offset_um"];
                    (v[0].as_f64().unwrap(), v[1].as_f64().unwrap())
                })
                .collect()
        })
        .collect()
}

#[test]
fn a_failed_session_resumes_with_exactly_its_missing_frames_and_one_result() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), vec![Fault::CameraTimeout(STALL_AT_GRAB)]);
    let mut c = d.subscribed();
    let (id, ev) = run_job(&mut c, job());
    assert!(
        matches!(ev.last(), Some(EventBody::Failed { .. })),
        "{ev:?}"
    );
    let a = d.session(&ev);
    let a_name = a.manifest.name.clone();
    assert_eq!(a.manifest.state, SessionState::Failed);
    let kept = STALL_AT_GRAB - 1;
    assert_eq!(a.steps.len() as u32, kept);
    let a_manifest = std::fs::read(a.dir.join("manifest.json")).unwrap();
    let a_steps = std::fs::read(a.dir.join("steps.csv")).unwrap();
    let planned: Vec<f64> = a
        .manifest
        .plan
        .runs
        .iter()
        .flat_map(|r| r.positions_um.clone())
        .collect();
    assert_eq!(planned.len() as u32, FRAMES);

    let reply = resume(&mut c, &a_name).unwrap();
    assert_eq!(reply["total_frames"], FRAMES);
    assert_eq!(reply["resumed_from"]["session"], a_name.as_str());
    assert_eq!(reply["resumed_from"]["first_index"], kept);
    let rid = job_id(&reply);
    let ev = events_until_end(&mut c, rid);
    assert_finished(&ev);
    // Step events carry the plan's indices and positions, from the first missing frame.
    let want: Vec<(u32, f64)> = (kept..FRAMES).map(|i| (i, planned[i as usize])).collect();
    assert_eq!(reported_steps(&ev), want);
    let b = d.session(&ev);
    assert_eq!(
        b.manifest.resumed_from,
        Some(ResumedFrom {
            session: a_name.clone(),
            first_index: kept
        })
    );
    assert_eq!(b.manifest.plan.first_index, kept);
    assert_eq!(b.manifest.plan.runs, a.manifest.plan.runs);
    assert_eq!(b.manifest.job, a.manifest.job);
    let rows: Vec<(u32, f64)> = b.steps.iter().map(|r| (r.index, r.position_um)).collect();
    assert_eq!(rows, want);
    assert_frames_decode(&b, (300, 200));
    // Across the two sessions: every plan index once, none lost, none repeated.
    let mut all: Vec<u32> = a.steps.iter().chain(&b.steps).map(|r| r.index).collect();
    all.sort();
    assert_eq!(all, (0..FRAMES).collect::<Vec<_>>());
    // The original is not written to.
    assert_eq!(
        std::fs::read(a.dir.join("manifest.json")).unwrap(),
        a_manifest
    );
    assert_eq!(std::fs::read(a.dir.join("steps.csv")).unwrap(), a_steps);
    assert!(!a.frame_path(kept).exists());
    // The frames the job took are counted over the plan.
    let st = c.request(&Request::Status { job_id: Some(rid) }).unwrap();
    assert_eq!(
        (st["frames_done"].as_u64(), st["total_frames"].as_u64()),
        (Some(12), Some(12))
    );

    // One result for every run, each from all 4 of its frames: run 0 from the original's
    // alone, run 1 from both sessions' (frames 4, 5 then 6, 7), run 2 from the new ones.
    let result = c.request(&Request::Result { job_id: rid }).unwrap()["result"].clone();
    let got = runs(&result);
    assert_eq!(got.len(), 3, "{result}");
    for (run, frames, processed, at) in &got {
        assert_eq!((*frames, *processed), (4, 4), "run {run}");
        // The steps list every frame of the run, in plan order.
        let base = *run as usize * 4;
        assert_eq!(at, &planned[base..base + 4].to_vec(), "run {run}");
    }
    assert!(result["study"].is_object(), "{result}");

    // A replay of the resumed session replays its own frames, at their plan indices.
    let (_, ev) = run_request(
        &mut c,
        &Request::Replay {
            session: b.manifest.name.clone(),
            processing: Default::default(),
        },
    );
    assert_finished(&ev);
    let idx: Vec<u32> = reported_steps(&ev).iter().map(|s| s.0).collect();
    assert_eq!(idx, (kept..FRAMES).collect::<Vec<_>>());

    // The same job uninterrupted (the stall was once): the same runs, the same offsets
    // within the sim's capture-to-capture scatter (4 frames at k = 4 on 300x200 frames of
    // 774 µm px: up to about 5 µm seen; a run missing half its frames or registered
    // wrongly is off by more, or has no result).
    let (_, ev) = run_job(&mut c, job());
    assert_finished(&ev);
    let whole = Session::open(&d.data.join(session_name(&ev))).unwrap();
    let whole = whole.result().unwrap();
    let (x, y) = (offsets(&whole), offsets(&result));
    assert_eq!(runs(&whole).len(), 3);
    for (run, (p, q)) in x.iter().zip(&y).enumerate() {
        assert_eq!(p.len(), q.len(), "run {run}");
        assert!(!p.is_empty(), "run {run}: no target");
        for (u, v) in p.iter().zip(q) {
            assert!(
                (u.0 - v.0).abs() < 10.0 && (u.1 - v.1).abs() < 10.0,
                "run {run}: {u:?} uninterrupted, {v:?} resumed"
            );
        }
    }
    let _ = id;
}

#[test]
fn sessions_that_cannot_be_resumed_are_refused_naming_why() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), vec![Fault::CameraTimeout(4)]);
    let mut c = d.subscribed();
    let (_, ev) = run_job(
        &mut c,
        JobSpec {
            process: false,
            ..job()
        },
    );
    let a = d.session(&ev);
    assert_eq!(a.steps.len(), 3);
    let (_, ev) = run_job(&mut c, capture_job(50.0, 2, 0));
    assert_finished(&ev);
    let done = session_name(&ev);

    let e = resume(&mut c, &done).unwrap_err();
    assert!(
        e.starts_with("rigd: rejected: session ") && e.contains("finished: nothing to resume"),
        "{e}"
    );
    let e = resume(&mut c, "nope").unwrap_err();
    assert_eq!(e, "rigd: not_found: no session nope");
    let e = resume(&mut c, "../etc").unwrap_err();
    assert!(e.contains("is not a session name"), "{e}");

    // Recorded on another scale: a copy of the failed session with its rig's scale changed.
    let other = copy_session(&d.data, &a, "other-scale", |m| {
        m["rig"]["scale_um_per_px"] = 700.0.into();
    });
    let e = resume(&mut c, &other).unwrap_err();
    assert!(
        e.starts_with(
            "rigd: rejected: session other-scale was recorded on another rig: its \
             scale was 700 µm/px, this rig's is "
        ),
        "{e}"
    );
    // A session whose manifest cannot be read.
    let unreadable = copy_session(&d.data, &a, "unreadable", |_| {});
    std::fs::write(d.data.join(&unreadable).join("manifest.json"), "{").unwrap();
    let e = resume(&mut c, &unreadable).unwrap_err();
    assert!(
        e.starts_with("rigd: rejected: session unreadable cannot be read: "),
        "{e}"
    );
    // A replay is not resumed.
    let replayed = copy_session(&d.data, &a, "a-replay", |m| {
        m["replay_of"] = a.manifest.name.clone().into();
    });
    let e = resume(&mut c, &replayed).unwrap_err();
    assert!(e.contains("a-replay is a replay"), "{e}");

    // A frame without its row, or cut short, counts as missing.
    let no_row = copy_session(&d.data, &a, "frame-without-row", |_| {});
    let frames = d.data.join(&no_row).join("frames");
    std::fs::copy(frames.join("000002.png"), frames.join("000003.png")).unwrap();
    let mut steps = std::fs::OpenOptions::new()
        .append(true)
        .open(d.data.join(&no_row).join("steps.csv"))
        .unwrap();
    std::io::Write::write_all(&mut steps, b"3,1580.5,0,scan,0,1580").unwrap();
    let cut = copy_session(&d.data, &a, "frame-cut-short", |_| {});
    let last = d.data.join(&cut).join("frames").join("000002.png");
    let bytes = std::fs::read(&last).unwrap();
    std::fs::write(&last, &bytes[..bytes.len() / 2]).unwrap();
    let lost = copy_session(&d.data, &a, "frame-lost", |_| {});
    std::fs::remove_file(d.data.join(&lost).join("frames").join("000001.png")).unwrap();
    for (name, first) in [(&no_row, 3), (&cut, 2), (&lost, 1)] {
        let r = resume(&mut c, name).unwrap();
        assert_eq!(r["resumed_from"]["first_index"], first, "{name}");
        let ev = events_until_end(&mut c, job_id(&r));
        assert_finished(&ev);
        let b = d.session(&ev);
        let idx: Vec<u32> = b.steps.iter().map(|r| r.index).collect();
        assert_eq!(idx, (first..FRAMES).collect::<Vec<_>>(), "{name}");
    }
    // `rigctl resume SESSION` follows the new job as submit does and ends with the session's
    // path; a job id resumes a paused job instead (no --detach there).
    let (ok, out, err) = rigctl(&d.bg.socket, &["resume", &a.manifest.name]);
    assert!(ok, "{out}{err}");
    assert!(
        err.contains(&format!(
            "resuming session {} from frame 3",
            a.manifest.name
        )),
        "{err}"
    );
    assert!(
        out.contains("(no measurements: the job was not processed)"),
        "{out}"
    );
    assert!(
        out.contains(&format!("session: {}", d.data.display())),
        "{out}"
    );
    let (ok, _, err) = rigctl(&d.bg.socket, &["resume", "nope"]);
    assert!(!ok && err.contains("no session nope"), "{err}");
    let (ok, _, err) = rigctl(&d.bg.socket, &["resume", "7", "--detach"]);
    assert!(
        !ok && err.contains("--detach is for resuming a session"),
        "{err}"
    );
    // The daemon keeps serving.
    c.request(&Request::Hello {}).unwrap();
}

/// `rigctl ARGS --socket SOCKET`: success, stdout, stderr.
fn rigctl(socket: &Path, args: &[&str]) -> (bool, String, String) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(args)
        .arg("--socket")
        .arg(socket)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// A copy of session `s` under the data root as `name`, its manifest changed by `f`.
fn copy_session(data: &Path, s: &Session, name: &str, f: impl FnOnce(&mut Value)) -> String {
    let to = data.join(name);
    std::fs::create_dir_all(to.join("frames")).unwrap();
    for e in std::fs::read_dir(s.dir.join("frames")).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join("frames").join(e.file_name())).unwrap();
    }
    std::fs::copy(s.dir.join("steps.csv"), to.join("steps.csv")).unwrap();
    let mut m: Value =
        serde_json::from_slice(&std::fs::read(s.dir.join("manifest.json")).unwrap()).unwrap();
    m["name"] = name.into();
    f(&mut m);
    std::fs::write(to.join("manifest.json"), serde_json::to_vec(&m).unwrap()).unwrap();
    name.to_string()
}

#[test]
fn a_session_left_incomplete_by_kill_9_resumes_after_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let (socket, data) = (dir.path().join("s.sock"), dir.path().join("data"));
    let mut child = RigdProcess::spawn_sim(&socket, &data);
    let mut c = Client::connect(&socket).unwrap();
    subscribe(&mut c);
    let id = submit(&mut c, capture_job(50.0, 20, 20));
    let (mut name, mut reported) = (String::new(), 0);
    while reported < 3 {
        let e = c.next_event().unwrap();
        match e.body {
            EventBody::Started { session, .. } if e.job_id == id => name = session,
            EventBody::Step { .. } if e.job_id == id => reported += 1,
            other => assert!(!other.is_terminal(), "{other:?}"),
        }
    }
    child.kill_9();
    let _child = RigdProcess::spawn_sim(&socket, &data);
    let a = Session::open(&data.join(&name)).unwrap();
    assert_eq!(a.manifest.state, SessionState::Incomplete);
    let kept = a.steps.len() as u32;
    assert!((3..20).contains(&kept), "{kept} frames kept");
    let mut c = Client::connect(&socket).unwrap();
    subscribe(&mut c);
    let r = resume(&mut c, &name).unwrap();
    assert_eq!(r["resumed_from"]["first_index"], kept);
    let ev = events_until_end(&mut c, job_id(&r));
    assert_finished(&ev);
    let b = session_of(&data, &ev);
    let mut all: Vec<(u32, f64)> = a
        .steps
        .iter()
        .chain(&b.steps)
        .map(|r| (r.index, r.position_um))
        .collect();
    all.sort_by_key(|x| x.0);
    let planned: Vec<(u32, f64)> = a.manifest.plan.runs[0]
        .positions_um
        .iter()
        .enumerate()
        .map(|(i, &p)| (i as u32, p))
        .collect();
    assert_eq!(all, planned);
    assert_frames_decode(&b, b.manifest.rig.frame_size);
}
