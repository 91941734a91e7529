//! Requests and clients as an adversary sends them, against the real `rigd` binary: a
//! preview at an absurd rate, a preview nobody reads, a job whose thread panics, cancels
//! racing a job's last frame, `stop` during homing, the live view of a paused job, `resume`
//! after `cancel`, and `rigctl` writing into a closed pipe.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::adversary::{capture_job, cpu_time, follow, open_fds, Line, Spawn};
use crate::support::instances::Logged;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `rigd --sim` (its GRBL emulator behind the axis) with `extra` arguments: the daemon,
/// its socket and its data root.
fn sim(dir: &Path, extra: &[&str]) -> (Logged, PathBuf, PathBuf) {
    let (sock, data) = (dir.join("rigd.sock"), dir.join("data"));
    let mut args = vec!["--sim", "--socket", s(&sock), "--data-root", s(&data)];
    args.extend_from_slice(extra);
    let d = Logged::spawn(&args, &[], &sock, &dir.join("rigd.log"));
    (d, sock, data)
}

fn error_of(reply: &Value) -> (&str, &str) {
    assert_eq!(reply["ok"], false, "{reply}");
    (
        reply["error"]["code"].as_str().unwrap(),
        reply["error"]["message"].as_str().unwrap(),
    )
}

#[test]
fn a_preview_at_an_absurd_rate_is_refused_and_leaks_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(env!("CARGO_BIN_EXE_rigd"), dir.path()).start();
    let fds = open_fds(d.pid());
    for rate in ["1e-300", "5e-324", "0.001", "-0.0", "1e308"] {
        for _ in 0..20 {
            let mut c = d.client();
            let r = c.request(&format!(r#"{{"kind": "preview", "max_fps": {rate}}}"#));
            let (code, msg) = error_of(&r);
            assert_eq!(code, "bad_request", "{r}");
            assert!(msg.contains("`max_fps` must be from 0.01 to 60"), "{msg}");
            // The connection goes on.
            assert_eq!(c.request(r#"{"kind": "hello"}"#)["ok"], true);
        }
    }
    std::thread::sleep(Duration::from_millis(300));
    assert!(
        open_fds(d.pid()) <= fds + 2,
        "{} fds, {fds} before",
        open_fds(d.pid())
    );
    // rigctl refuses it before sending anything.
    let out = Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(["view", "--socket", s(&d.socket), "--fps", "1e-300"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("must be from 0.01 to 60"), "{err}");
}

#[test]
fn a_preview_nobody_reads_costs_no_cpu_and_is_dropped() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn {
        daemon_toml: "stalled_client_ms = 500",
        ..Spawn::new(env!("CARGO_BIN_EXE_rigd"), dir.path())
    }
    .start();
    let mut greedy = d.client();
    greedy.send(r#"{"kind": "preview", "max_fps": 60, "scale": 1}"#);
    // Its frames fill the socket's buffers, then one waits past the stall time.
    std::thread::sleep(Duration::from_secs(4));
    let cpu = cpu_time(d.pid());
    std::thread::sleep(Duration::from_secs(2));
    let busy = cpu_time(d.pid()) - cpu;
    assert!(busy < Duration::from_millis(400), "{busy:?} of CPU in 2 s");
    let (got, closed) = greedy.drain(Duration::from_secs(10));
    assert!(closed, "the daemon closes the connection");
    assert!(got.iter().any(|v| v["event"] == "preview"), "it had frames");
    assert!(
        d.log_text().contains("reads none of its preview"),
        "{}",
        d.log_text()
    );
    // Another client is served as ever.
    let mut c = d.client();
    c.send(r#"{"kind": "preview", "max_fps": 10}"#);
    assert_eq!(c.read().unwrap()["ok"], true);
    assert_eq!(c.read().unwrap()["event"], "preview");
}

#[test]
fn a_job_whose_thread_panics_fails_and_the_worker_runs_the_next() {
    let dir = tempfile::tempdir().unwrap();
    let (mut d, sock, data) = sim(dir.path(), &["--fault", "panic@2"]);
    let mut c = Line::connect(&sock);
    c.request(r#"{"kind": "subscribe"}"#);
    let id = c.request(&capture_job(4, 0, "panics"))["result"]["job_id"]
        .as_u64()
        .unwrap();
    let ev = follow(&mut c, id);
    let end = ev.last().unwrap();
    assert_eq!(end["event"], "failed", "{end}");
    let reason = end["reason"].as_str().unwrap();
    assert!(
        reason.starts_with("internal error: the step engine panicked: injected panic on move 2"),
        "{reason}"
    );
    assert_eq!(end["detail"]["kind"], "internal", "{end}");
    let session = end["session"].as_str().unwrap();
    let m: Value =
        serde_json::from_slice(&std::fs::read(data.join(session).join("manifest.json")).unwrap())
            .unwrap();
    assert_eq!(m["state"], "failed", "the session is closed: {m}");
    assert_eq!(m["frames_captured"], 1);
    // The worker goes on: the next job runs and the daemon still answers.
    let id = c.request(&capture_job(3, 0, "after"))["result"]["job_id"]
        .as_u64()
        .unwrap();
    assert_eq!(follow(&mut c, id).last().unwrap()["event"], "finished");
    assert_eq!(c.request(r#"{"kind": "status"}"#)["ok"], true);
    assert!(d.stop_with(libc::SIGTERM).success());
}

#[test]
fn a_cancelling_job_always_ends_cancelled_and_a_late_cancel_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(env!("CARGO_BIN_EXE_rigd"), dir.path()).start();
    let mut c = d.client();
    c.request(r#"{"kind": "subscribe"}"#);
    let mut answers = std::collections::BTreeMap::<String, usize>::new();
    for i in 0..60 {
        let id = c.request(&capture_job(1, 0, "one"))["result"]["job_id"]
            .as_u64()
            .unwrap();
        // A few ms in: the cancel races the job's only frame and its closing.
        std::thread::sleep(Duration::from_millis(i % 12));
        let r = c.request(&format!(r#"{{"kind": "cancel", "job_id": {id}}}"#));
        let end = follow(&mut c, id).pop().unwrap();
        let said = match r["ok"].as_bool() {
            Some(true) => r["result"]["state"].as_str().unwrap().to_string(),
            _ => r["error"]["code"].as_str().unwrap().to_string(),
        };
        let ended = end["event"].as_str().unwrap();
        match said.as_str() {
            "cancelling" | "cancelled" => assert_eq!(ended, "cancelled", "{r} {end}"),
            "rejected" => {
                let msg = r["error"]["message"].as_str().unwrap();
                assert!(msg.contains("too late to cancel"), "{msg}");
                assert_eq!(ended, "finished", "{r} {end}");
            }
            // It had ended before the cancel arrived.
            "not_found" => assert_eq!(ended, "finished", "{r} {end}"),
            other => panic!("{other}: {r}"),
        }
        *answers.entry(format!("{said} -> {ended}")).or_default() += 1;
    }
    assert!(
        answers.keys().any(|k| k.starts_with("cancelling")),
        "{answers:?}"
    );
}

#[test]
fn stop_aborts_a_homing_cycle_and_says_the_axis_is_in_alarm() {
    let dir = tempfile::tempdir().unwrap();
    let (_d, sock, _) = sim(dir.path(), &[]);
    let mut c = Line::connect(&sock);
    // 60 mm out: homing back takes 3 s at the sim's 20 mm/s.
    let r = c.request(r#"{"kind": "move", "stage": "axis", "to_um": 60000}"#);
    assert_eq!(r["ok"], true, "{r}");
    let homing = std::thread::spawn(move || {
        let mut h = Line::connect(&sock);
        let t = Instant::now();
        (h.request(r#"{"kind": "home"}"#), t.elapsed(), sock)
    });
    std::thread::sleep(Duration::from_millis(600));
    let stop = c.request(r#"{"kind": "stop"}"#);
    assert_eq!(stop["result"]["stopping"], true, "{stop}");
    let msg = stop["result"]["message"].as_str().unwrap();
    assert!(msg.contains("stopping the homing cycle"), "{msg}");
    let (home, took, sock) = homing.join().unwrap();
    assert!(
        took < Duration::from_millis(2000),
        "home answered after {took:?}"
    );
    let (code, msg) = error_of(&home);
    assert_eq!(code, "hardware", "{home}");
    assert!(
        msg.contains("homing stopped by `stop`") && msg.contains("alarm"),
        "{msg}"
    );
    // It stopped on its way: neither at 60 mm nor home.
    let pos = Line::connect(&sock).request(r#"{"kind": "position"}"#);
    let at = pos["result"]["axis"]["position_um"].as_f64().unwrap();
    assert!(at > 5000.0 && at < 55000.0, "{pos}");
    assert_eq!(pos["result"]["axis"]["state"], "alarm", "{pos}");
    // The fault is cleared the usual way.
    let r = c.request(r#"{"kind": "unlock"}"#);
    assert_eq!(r["ok"], true, "{r}");
}

/// The status of job `id`.
fn status(c: &mut Line, id: u64) -> Value {
    c.request(&format!(r#"{{"kind": "status", "job_id": {id}}}"#))["result"].clone()
}

#[test]
fn a_paused_job_serves_the_live_view_stands_its_eta_still_and_is_not_resumed_once_cancelled() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(env!("CARGO_BIN_EXE_rigd"), dir.path()).start();
    let mut c = d.client();
    c.request(r#"{"kind": "subscribe"}"#);
    let id = c.request(&capture_job(400, 20, "long"))["result"]["job_id"]
        .as_u64()
        .unwrap();
    let r = c.request(&format!(r#"{{"kind": "pause", "job_id": {id}}}"#));
    assert_eq!(r["ok"], true, "{r}");
    while c.read().unwrap()["event"] != "paused" {}
    // A snap answers at once with a fresh frame, the job's.
    let t = Instant::now();
    let snap = d.client().request(r#"{"kind": "snap"}"#);
    assert_eq!(snap["ok"], true, "{snap}");
    assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
    assert_eq!(snap["result"]["job_id"], id, "{snap}");
    // A preview gets frames.
    let mut v = d.client();
    v.send(r#"{"kind": "preview", "max_fps": 20}"#);
    assert_eq!(v.read().unwrap()["ok"], true);
    for _ in 0..3 {
        assert_eq!(v.read().unwrap()["event"], "preview");
    }
    // The ETA stands still.
    let eta = status(&mut c, id)["eta_s"].as_f64().unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    let later = status(&mut c, id)["eta_s"].as_f64().unwrap();
    assert!((later - eta).abs() < 0.05, "{eta} then {later}");
    // Cancelled, it is not resumed.
    c.send(&format!(r#"{{"kind": "cancel", "job_id": {id}}}"#));
    c.send(&format!(r#"{{"kind": "resume", "job_id": {id}}}"#));
    let mut replies = Vec::new();
    while replies.len() < 2 {
        let l = c.read().unwrap();
        if l["type"] == "reply" {
            replies.push(l);
        }
    }
    assert_eq!(replies[0]["ok"], true, "{}", replies[0]);
    let (code, _) = error_of(&replies[1]);
    assert_eq!(code, "rejected", "{}", replies[1]);
    assert_eq!(follow(&mut c, id).last().unwrap()["event"], "cancelled");
}

/// Run rigctl `args` with stdout a pipe whose reader has already gone.
fn into_closed_pipe(args: &[&str]) -> std::process::Output {
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader);
    Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(args)
        .stdout(Stdio::from(writer))
        .stderr(Stdio::piped())
        .output()
        .unwrap()
}

#[test]
fn rigctl_into_a_closed_pipe_ends_quietly() {
    let out = into_closed_pipe(&["schema"]);
    assert!(out.status.success(), "{out:?}");
    assert_eq!(String::from_utf8_lossy(&out.stderr), "");
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(env!("CARGO_BIN_EXE_rigd"), dir.path()).start();
    let mut c = d.client();
    c.request(r#"{"kind": "subscribe"}"#);
    for _ in 0..3 {
        let id = c.request(&capture_job(1, 0, "x"))["result"]["job_id"]
            .as_u64()
            .unwrap();
        follow(&mut c, id);
    }
    for args in [vec!["list"], vec!["status"]] {
        let mut args = args;
        args.extend(["--socket", s(&d.socket)]);
        let out = into_closed_pipe(&args);
        assert!(out.status.success(), "{args:?}: {out:?}");
        assert_eq!(String::from_utf8_lossy(&out.stderr), "", "{args:?}");
    }
    // A daemon that is not there is still an error worth saying.
    let out = into_closed_pipe(&["list", "--socket", s(&dir.path().join("none.sock"))]);
    assert!(!out.status.success());
    assert!(!out.stderr.is_empty());
}

/// ±0, denormals, the extremes, ordinary values, and numbers JSON cannot hold, as JSON text.
fn extreme() -> impl proptest::strategy::Strategy<Value = String> {
    use proptest::prelude::*;
    prop_oneof![
        Just("0".to_string()),
        Just("-0.0".to_string()),
        Just("5e-324".to_string()),
        Just("1e308".to_string()),
        Just("-1e308".to_string()),
        Just("1e-308".to_string()),
        Just("1e400".to_string()),
        Just("NaN".to_string()),
        Just("-Infinity".to_string()),
        Just("18446744073709551616".to_string()),
        any::<f64>().prop_map(|v| format!("{v:e}")),
        (-100.0f64..100.0).prop_map(|v| v.to_string()),
    ]
}

/// Every request that takes a number, with `V` where the number goes.
const NUMERIC_REQUESTS: &[&str] = &[
    r#"{"kind": "preview", "max_fps": V}"#,
    r#"{"kind": "snap", "scale": V}"#,
    r#"{"kind": "move", "stage": "axis", "to_um": V}"#,
    r#"{"kind": "move", "stage": "axis", "by_um": V}"#,
    r#"{"kind": "submit", "job": {"steps": 2, "step_um": V, "settle_ms": 0, "process": false}}"#,
    r#"{"kind": "submit", "job": {"steps": 2, "step_um": 10, "start_um": V, "process": false}}"#,
    r#"{"kind": "submit", "job": {"steps": 2, "step_um": 10, "repeats": 2, "interval_s": V, "process": false}}"#,
    r#"{"kind": "submit", "job": {"steps": V, "step_um": 10, "process": false}}"#,
    r#"{"kind": "list", "limit": V}"#,
    r#"{"kind": "cancel", "job_id": V}"#,
    r#"{"kind": "status", "job_id": V}"#,
    r#"{"kind": "pause", "job_id": V}"#,
];

#[test]
fn extreme_numbers_in_every_request_get_a_reply_and_the_daemon_serves_on() {
    use proptest::test_runner::{Config, TestRunner};
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(env!("CARGO_BIN_EXE_rigd"), dir.path()).start();
    let mut runner = TestRunner::new(Config::with_cases(40));
    runner
        .run(&extreme(), |v| {
            let mut c = d.client();
            for template in NUMERIC_REQUESTS {
                let r = c.request(&template.replace('V', &v));
                assert!(r["ok"].is_boolean(), "{template} with {v}: {r}");
                if let Some(id) = r["result"]["job_id"].as_u64() {
                    c.request(&format!(r#"{{"kind": "cancel", "job_id": {id}}}"#));
                }
                c.request(r#"{"kind": "preview_stop"}"#);
            }
            assert_eq!(c.request(r#"{"kind": "hello"}"#)["ok"], true, "with {v}");
            Ok(())
        })
        .unwrap();
    assert!(!d.log_text().contains("panicked"), "{}", d.log_text());
}
