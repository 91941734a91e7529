//! Clients against a newer daemon: a fake rigd on a real Unix socket answers as a later
//! protocol-1 daemon might, with event kinds, line types and fields (at the top and nested)
//! these clients do not know, mid-stream. `rigctl submit`, `rigctl watch` and
//! docs/examples/client.py must skip and ignore them and still follow the job to its end.

use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const JOB: u64 = 7;
/// As many as docs/examples/client.py asks for.
const FRAMES: u32 = 5;
const SESSION: &str = "20261201T000000Z-job7";

fn reply(id: &Value, result: Value) -> Value {
    json!({"type": "reply", "v": 1, "id": id, "ok": true, "result": result, "served_by": "rigd 9"})
}

/// What a newer daemon sends after accepting job `JOB`, its own kinds and fields included.
fn job_events() -> Vec<Value> {
    let ev = |body: Value| {
        let mut e = json!({"type": "event", "v": 1, "job_id": JOB, "at_s": 12.5});
        e.as_object_mut()
            .unwrap()
            .extend(body.as_object().unwrap().clone());
        e
    };
    let mut v = vec![
        json!({"type": "event", "v": 1, "job_id": 99, "event": "hologram", "png_b64": "iVBORw0K"}),
        json!({"type": "notice", "v": 1, "text": "a line type of protocol 1.x"}),
        ev(
            json!({"event": "accepted", "queue_position": 0, "total_frames": FRAMES,
            "job": {"step_um": 50.0, "steps": FRAMES, "plan": {"kind": "grid", "snake": true}}}),
        ),
        ev(json!({"event": "levitated", "at_index": 0, "reason": "asked"})),
        ev(json!({"event": "landed"})),
        ev(
            json!({"event": "started", "session": SESSION, "total_frames": FRAMES,
            "started_at": "2026-12-01T00:00:00Z"}),
        ),
    ];
    for i in 0..FRAMES {
        v.push(ev(
            json!({"event": "step", "index": i, "run": 0, "case": "scan", "repeat": 0,
            "commanded_um": 50.0 * i as f64, "axis_um": 50.0 * i as f64,
            "timings": {"move_ms": 1.0, "settle_ms": 0.0, "grab_ms": 1.0, "write_ms": 0.5},
            "total_frames": FRAMES, "position": {"axis_um": 1.0, "piezo_um": 2.0},
            "eta_s": 1.0}),
        ));
        v.push(ev(
            json!({"event": "hologram", "frame": {"width": 4, "height": 2}, "targets": []}),
        ));
    }
    v.push(ev(
        json!({"event": "result", "run": 0, "case": "scan", "repeat": 0,
        "objects": 2, "offsets_um": [[1.0, 2.0]]}),
    ));
    v.push(ev(json!({"event": "finished", "session": SESSION,
        "session_path": "/data/20261201T000000Z-job7", "elapsed_s": 0.1})));
    v
}

/// The newer daemon's answer to one request, and whether the job's events follow it.
fn answer(req: &Value) -> (Value, bool) {
    let id = &req["id"];
    let status = json!({"job_id": JOB, "state": "running", "label": null, "replay_of": null,
        "session": null, "frames_done": 0, "total_frames": FRAMES, "reason": null,
        "eta_s": 2.0});
    match req["kind"].as_str().unwrap_or_default() {
        "hello" => (
            reply(
                id,
                json!({"protocol": 1, "rigd": "9.0.0", "data_root": "/data",
                "rig": {"mode": "sim", "axis_limits_um": [0.0, 1e5], "piezo_limits_um": null,
                    "default_start_um": 0.0, "scale_um_per_px": 10.0, "frame_size": [48, 32],
                    "job_defaults": {}, "stages": ["axis", "piezo", "z"]},
                "rig_state": {"state": "ready", "since": "now"},
                "capabilities": {"requests": ["hello", "submit", "paint"], "events": ["paused"]}}),
            ),
            false,
        ),
        "submit" if req["job"]["step_um"] == 0.0 => (
            json!({"type": "reply", "v": 1, "id": id, "ok": false,
                "error": {"code": "quota_exceeded", "message": "zero step", "hint": "step"}}),
            false,
        ),
        "submit" => (
            reply(
                id,
                json!({"job_id": JOB, "queue_position": 0, "total_frames": FRAMES,
                "job": {"step_um": 50.0, "steps": FRAMES, "plan": {"kind": "line"}},
                "eta_s": 3.0}),
            ),
            true,
        ),
        "subscribe" => {
            let one = req["job_id"].as_u64();
            let body = json!({"subscribed": one, "status": one.map(|_| status.clone())});
            (reply(id, body), one.is_some())
        }
        "result" => (
            reply(
                id,
                json!({"job_id": JOB, "session": SESSION, "state": "finished", "reason": null,
                "result": null, "path": "/data/x"}),
            ),
            false,
        ),
        "status" => (reply(id, status), false),
        _ => (reply(id, json!({})), false),
    }
}

fn serve(stream: UnixStream) {
    let mut out = stream.try_clone().unwrap();
    for line in BufReader::new(stream).lines() {
        let Ok(line) = line else { return };
        let req: Value = serde_json::from_str(&line).unwrap();
        let (r, events) = answer(&req);
        let mut lines = vec![r];
        if events {
            lines.extend(job_events());
        }
        for l in lines {
            if writeln!(out, "{l}").is_err() {
                return;
            }
        }
    }
}

/// The fake newer daemon on `dir/rigd.sock`, serving every connection until the test ends.
fn fake_rigd(dir: &Path) -> PathBuf {
    let path = dir.join("rigd.sock");
    let listener = UnixListener::bind(&path).unwrap();
    std::thread::spawn(move || {
        for s in listener.incoming().flatten() {
            std::thread::spawn(move || serve(s));
        }
    });
    path
}

fn rigctl(socket: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(args)
        .arg("--socket")
        .arg(socket)
        .env("RUST_LOG", "debug")
        .output()
        .unwrap()
}

fn text(o: &Output) -> String {
    format!(
        "status {}\nstdout:\n{}\nstderr:\n{}",
        o.status,
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

#[test]
fn rigctl_submit_and_watch_follow_a_newer_daemon_to_the_end() {
    let dir = tempfile::tempdir().unwrap();
    let socket = fake_rigd(dir.path());
    for args in [
        &["submit", "--steps", "5", "--step-um", "50"][..],
        &["watch", "7"][..],
    ] {
        let o = rigctl(&socket, args);
        let all = text(&o);
        assert!(o.status.success(), "rigctl {args:?}: {all}");
        assert!(all.contains("finished") && all.contains(SESSION), "{all}");
        assert!(!all.contains("unreadable"), "{all}");
    }
}

#[test]
fn a_known_event_without_its_required_fields_is_still_an_error() {
    // Tolerance is for what is new, not for a broken line: a `step` without `index`.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rigd.sock");
    let listener = UnixListener::bind(&path).unwrap();
    std::thread::spawn(move || {
        let (s, _) = listener.accept().unwrap();
        let mut out = s.try_clone().unwrap();
        let mut lines = BufReader::new(s).lines();
        let req: Value = serde_json::from_str(&lines.next().unwrap().unwrap()).unwrap();
        let (r, _) = answer(&req);
        writeln!(out, "{r}").unwrap();
        writeln!(out, r#"{{"type":"event","v":1,"job_id":7,"event":"step"}}"#).unwrap();
        let _ = lines.next(); // hold the connection until rigctl leaves
    });
    let o = rigctl(&path, &["watch", "7"]);
    let all = text(&o);
    assert!(!o.status.success(), "{all}");
    assert!(
        all.contains("unreadable line from rigd") && all.contains("index"),
        "{all}"
    );
}

#[test]
fn the_python_client_follows_a_newer_daemon_to_the_end() {
    if Command::new("python3").arg("--version").output().is_err() {
        crate::support::skip::skipped(
            "the_python_client_follows_a_newer_daemon_to_the_end",
            "no python3",
        );
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let socket = fake_rigd(dir.path());
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/examples/client.py");
    let o = Command::new("python3")
        .arg(script)
        .arg(&socket)
        .output()
        .unwrap();
    let all = text(&o);
    assert!(o.status.success(), "{all}");
    assert!(all.contains(&format!("job {JOB} finished")), "{all}");
    assert!(all.contains(&format!("session {SESSION}")), "{all}");
    assert!(
        all.contains("refused as expected: quota_exceeded: zero step"),
        "{all}"
    );
    assert_eq!(all.matches("  step ").count(), FRAMES as usize, "{all}");
}
