//! Protocol strictness against the real `rigd` binary, and the simulated interferometer's
//! log while the daemon idles. None of these is accepted: a job sent as an array, unknown
//! fields in `hello`/`list`, duplicate keys (the last winning), ids beyond 2^53 altered, job
//! ids repeated after a restart, and the sim XL-80's log growing (~24 kB/s) with no job
//! running.

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::adversary::{capture_job, follow, Spawn};
use std::time::Duration;

/// The binary under test: this build's, or `RIGD_BIN` (to see the attacks against another
/// build).
fn rigd() -> String {
    std::env::var("RIGD_BIN").unwrap_or_else(|_| env!("CARGO_BIN_EXE_rigd").to_string())
}

#[test]
fn malformed_shapes_are_refused_and_nothing_runs() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(rigd(), dir.path()).start();
    let mut c = d.client();
    let cases: &[(&str, &str)] = &[
        // serde takes a struct as an array of its fields in order: this one would run.
        (
            r#"{"id":1,"kind":"submit","job":["axis",10.0,3]}"#,
            "`job` must be a JSON object, got an array",
        ),
        (
            r#"{"id":2,"kind":"hello","please":true}"#,
            "unknown field `please`",
        ),
        (
            r#"{"id":3,"kind":"list","all":true}"#,
            "unknown field `all`",
        ),
        (
            r#"{"id":4,"kind":"submit","job":{"steps":1,"step_um":10,"steps":3000,"process":false}}"#,
            r#"duplicate key "steps" in `job`"#,
        ),
        (
            r#"{"id":5,"kind":"status","kind":"cancel","job_id":1}"#,
            r#"duplicate key "kind" in the request"#,
        ),
        // Manual control's requests, as strict as the others: else a second target would win.
        (
            r#"{"id":6,"kind":"move","stage":"axis","to_um":10,"to_um":200000}"#,
            r#"duplicate key "to_um" in the request"#,
        ),
        (
            r#"{"id":7,"kind":"move","stage":"axis","to_um":10,"by_um":10}"#,
            "not both",
        ),
        (
            r#"{"id":8,"kind":"stop","now":true}"#,
            "unknown field `now`",
        ),
        (
            r#"{"id":9,"kind":"position","stage":"axis"}"#,
            "unknown field `stage`",
        ),
        (r#"{"id":10,"kind":"pause","job_id":1.5}"#, "invalid type"),
        (r#"{"id":11,"kind":"resume"}"#, "missing field `job_id`"),
        (
            r#"{"id":12,"kind":"resume_session","session":7}"#,
            "invalid type",
        ),
        (
            r#"{"id":13,"kind":"resume_session","job_id":1}"#,
            "unknown field `job_id`",
        ),
    ];
    for (line, needle) in cases {
        let r = c.request(line);
        assert_eq!(r["error"]["code"], "bad_request", "{line}: {r}");
        let m = r["error"]["message"].as_str().unwrap();
        assert!(m.contains(needle), "{line}: {m:?} should name {needle:?}");
    }
    let st = c.request(r#"{"kind":"status"}"#);
    assert_eq!(st["result"]["running"], serde_json::Value::Null);
    assert_eq!(st["result"]["queued"], serde_json::json!([]));
    assert!(
        !d.data.exists()
            || std::fs::read_dir(&d.data).unwrap().all(|e| e
                .unwrap()
                .file_name()
                .to_string_lossy()
                .starts_with('.'))
    );
}

#[test]
fn ids_come_back_exactly_or_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(rigd(), dir.path()).start();
    let mut c = d.client();
    for id in [
        r#""a-string""#,
        "9007199254740991",
        "-9007199254740991",
        "7",
    ] {
        let line = format!(r#"{{"id":{id},"kind":"hello"}}"#);
        c.send(&line);
        let mut raw = String::new();
        std::io::BufRead::read_line(&mut c.r, &mut raw).unwrap();
        // The id's very text comes back.
        assert!(raw.contains(&format!(r#""id":{id}"#)), "{raw}");
    }
    for id in [
        "9007199254740993",
        "123456789012345678901234567890",
        "2.5",
        "1e2",
        "null",
    ] {
        let r = c.request(&format!(r#"{{"id":{id},"kind":"hello"}}"#));
        assert_eq!(r["error"]["code"], "bad_request", "{id}: {r}");
        assert!(r.get("id").is_none(), "{r}");
        let m = r["error"]["message"].as_str().unwrap();
        assert!(
            m.contains("`id` must be a string or an integer within"),
            "{m}"
        );
    }
}

/// Job 2 is cancelled while queued (it never makes a session), the daemon restarts: the next
/// id is not the highest on disk + 1, which would hand out 2 again.
#[test]
fn job_ids_never_repeat_across_restarts() {
    let dir = tempfile::tempdir().unwrap();
    let mut d = Spawn::new(rigd(), dir.path()).start();
    let mut c = d.client();
    c.request(r#"{"kind":"subscribe"}"#);
    let long = c.request(&capture_job(2000, 5, "long"))["result"]["job_id"]
        .as_u64()
        .unwrap();
    let queued = c.request(&capture_job(1, 0, "queued"))["result"]["job_id"]
        .as_u64()
        .unwrap();
    let r = c.request(&format!(r#"{{"kind":"cancel","job_id":{queued}}}"#));
    assert_eq!(r["result"]["state"], "cancelled", "{r}");
    c.request(&format!(r#"{{"kind":"cancel","job_id":{long}}}"#));
    follow(&mut c, long);
    // A crash, not a clean stop: the counter was on disk before the ids were handed out.
    d.kill_9();
    drop(c);
    let d = Spawn::new(rigd(), dir.path()).start();
    let mut c = d.client();
    let next = c.request(&capture_job(1, 0, "after"))["result"]["job_id"]
        .as_u64()
        .unwrap();
    assert!(next > queued, "job id {next} after {long} and {queued}");
}

/// The sim's XL-80 logs only while a job runs: its file stays the same size while the
/// daemon idles, at start and after a job.
#[test]
fn the_simulated_interferometer_log_does_not_grow_while_idle() {
    let dir = tempfile::tempdir().unwrap();
    let rig = format!(
        "{}\n[xl80]\npath = \"capture.csv\"\nformat = \"csv\"\npoll_ms = 5\n",
        crate::support::adversary::SMALL_SIM_RIG
    );
    let d = Spawn {
        rig_toml: &rig,
        ..Spawn::new(rigd(), dir.path())
    }
    .start();
    let log = dir.path().join("capture.csv");
    let size = || std::fs::metadata(&log).map(|m| m.len()).unwrap_or(0);
    let idle = |what: &str| {
        let a = size();
        std::thread::sleep(Duration::from_millis(1500));
        let b = size();
        // A log written at 1 kHz while idle would grow ~36 kB in 1.5 s.
        assert_eq!(a, b, "the log grew {} bytes in 1.5 s {what}", b - a);
    };
    idle("after the start");
    let mut c = d.client();
    c.request(r#"{"kind":"subscribe"}"#);
    let id = c.request(&capture_job(20, 5, "laser"))["result"]["job_id"]
        .as_u64()
        .unwrap();
    let events = follow(&mut c, id);
    assert_eq!(events.last().unwrap()["event"], "finished", "{events:?}");
    // The job's readings are in its session: the log was written while it ran.
    let with_reading = events
        .iter()
        .filter(|e| e["event"] == "step" && e["interferometer_um"].is_number())
        .count();
    assert_eq!(with_reading, 20);
    assert!(size() > 1000, "the job's capture is in the log");
    idle("after a job");
}
