//! Clients as an adversary writes them, against the real `rigd` binary (resources): a flood
//! of idle connections at a 1024-fd limit, a client that pipelines requests and reads
//! nothing, subscribers that read too slowly, `list` over many sessions, jobs whose
//! processing would not fit in memory. The CPU and RSS figures of the same
//! attacks are in `benches/adversarial.rs` (docs/performance.md).

#![cfg(feature = "sim")] // the simulated rig (default feature)

use crate::support::adversary::{capture_job, follow, idle_flood, Spawn};
use serde_json::Value;
use std::time::{Duration, Instant};

/// The binary under test: this build's, or `RIGD_BIN` (to see the attacks against another
/// build).
fn rigd() -> String {
    std::env::var("RIGD_BIN").unwrap_or_else(|_| env!("CARGO_BIN_EXE_rigd").to_string())
}

/// 1100 idle connections at the common 1024-fd soft limit while a job runs. What it guards
/// against: every accept failing with EMFILE in a tight loop (~90% CPU, ~900 000 log lines
/// in 5 s), new clients stalled and the job failed with "Too many open files".
#[test]
fn an_fd_flood_leaves_the_job_whole_the_log_short_and_new_clients_served() {
    crate::support::adversary::raise_fd_limit(1200);
    let dir = tempfile::tempdir().unwrap();
    let mut d = Spawn {
        nofile: Some(1024),
        ..Spawn::new(rigd(), dir.path())
    }
    .start();
    let mut sub = d.client();
    sub.request(r#"{"kind":"subscribe"}"#);
    // 300 frames of 48x32 at ~10 ms a step: the job runs through the flood.
    let frames = 300;
    let r = sub.request(&capture_job(frames, 5, "under fire"));
    let id = r["result"]["job_id"].as_u64().unwrap();
    let flood = idle_flood(&d.socket, 1100);
    assert!(flood.len() >= 1000, "only {} connections made", flood.len());
    // A client over the limit is told why in one line and closed.
    let mut late = d.client();
    let (lines, closed) = late.drain(Duration::from_secs(5));
    assert!(closed, "a refused client is closed");
    assert_eq!(lines.len(), 1, "{lines:?}");
    assert_eq!(lines[0]["error"]["code"], "unavailable", "{}", lines[0]);
    let msg = lines[0]["error"]["message"].as_str().unwrap();
    assert!(msg.starts_with("too many connections (64"), "{msg}");
    // The job is unaffected: every frame on disk and reported.
    let events = follow(&mut sub, id);
    let end = events.last().unwrap();
    assert_eq!(end["event"], "finished", "{end}");
    let steps = events.iter().filter(|e| e["event"] == "step").count();
    assert_eq!(steps, frames as usize);
    let session = end["session"].as_str().unwrap();
    let on_disk = std::fs::read_dir(d.data.join(session).join("frames"))
        .unwrap()
        .count();
    assert_eq!(on_disk, frames as usize);
    // The flood goes away: a new client is served at once (within 1 s).
    drop(flood);
    let t = Instant::now();
    loop {
        let mut c = d.client();
        c.send(r#"{"kind":"hello"}"#);
        if c.read().is_some_and(|r| r["ok"] == true) {
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(1),
            "not served within 1 s"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    let served_after = t.elapsed();
    drop(sub);
    d.stop();
    // Refusals are logged once a second with a count, not once each.
    let lines = d.log_lines();
    assert!(lines < 1000, "{lines} log lines:\n{}", d.log_text());
    eprintln!("served {served_after:?} after the flood closed; {lines} log lines");
}

/// 300 pipelined `list` requests, never read. The daemon stops reading while the client's
/// queue is full and then disconnects it, logging why; other clients are served meanwhile.
/// (Replies queued without bound would take 1.5 GB for 150.)
#[test]
fn a_client_that_reads_nothing_is_cut_off_and_others_are_served() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn {
        daemon_toml: "output_queue_bytes = 65536\nstalled_client_ms = 500",
        ..Spawn::new(rigd(), dir.path())
    }
    .start();
    // Some sessions, so that each reply is a few kB.
    let mut c = d.client();
    c.request(r#"{"kind":"subscribe"}"#);
    for _ in 0..20 {
        let id = c.request(&capture_job(1, 0, &"x".repeat(200)))["result"]["job_id"]
            .as_u64()
            .unwrap();
        follow(&mut c, id);
    }
    let mut greedy = d.client();
    let one = serde_json::to_vec(&serde_json::json!({"kind": "list"})).unwrap();
    let reply_bytes = {
        let mut probe = d.client();
        probe
            .request(std::str::from_utf8(&one).unwrap())
            .to_string()
            .len()
    };
    assert!(reply_bytes > 5000, "{reply_bytes}");
    // Writes may block once the daemon stops reading: send from a thread.
    let mut w = greedy.w.try_clone().unwrap();
    let sender = std::thread::spawn(move || {
        use std::io::Write;
        let mut sent = 0;
        for _ in 0..300 {
            if w.write_all(&one).and_then(|()| w.write_all(b"\n")).is_err() {
                break;
            }
            sent += 1;
        }
        sent
    });
    // Meanwhile others are served.
    std::thread::sleep(Duration::from_millis(200));
    assert_eq!(d.client().request(r#"{"kind":"hello"}"#)["ok"], true);
    // It is cut off once its queue stays full for the stall time (0.5 s here).
    std::thread::sleep(Duration::from_secs(2));
    let (got, closed) = greedy.drain(Duration::from_secs(10));
    let _ = sender.join();
    assert!(closed, "the daemon closes the connection");
    // What it got is what the kernel's socket buffers and the 64 KiB queue held, not 300
    // replies.
    let replies = got.iter().filter(|v| v["type"] == "reply").count();
    assert!(replies < 300, "{replies} replies");
    assert!(
        d.log_text()
            .contains("disconnecting a client that reads none of its replies"),
        "{}",
        d.log_text()
    );
}

/// Subscribers that read nothing while jobs with 20 kB labels go by. Each has a
/// byte-bounded queue (queues of up to 1024 lines would let 60 of them take 1.9 GB): a slow
/// one loses events, is told how many once it catches up, and then gets events again.
#[test]
fn a_slow_subscriber_loses_events_with_one_notice_and_a_fast_one_loses_none() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn {
        daemon_toml: "output_queue_bytes = 65536",
        ..Spawn::new(rigd(), dir.path())
    }
    .start();
    // Jobs are submitted on their own connection: the subscribers only read events.
    let mut ctl = d.client();
    let mut fast = d.client();
    fast.request(r#"{"kind":"subscribe"}"#);
    let mut slow = d.client();
    slow.request(r#"{"kind":"subscribe"}"#);
    let label = "y".repeat(40_000);
    let mut total = 0;
    // 40 jobs x (accepted with the 40 kB label, started, calibration, step, finished):
    // 1.6 MB, far more than the 64 KiB queue and the kernel's socket buffers (~210 kB).
    for _ in 0..40 {
        let id = ctl.request(&capture_job(1, 0, &label))["result"]["job_id"]
            .as_u64()
            .unwrap();
        total += follow(&mut fast, id).len();
    }
    assert_eq!(total, 200);
    // Now the slow one reads: what was queued, one notice, nothing after it yet.
    slow.w
        .set_read_timeout(Some(Duration::from_millis(500)))
        .unwrap();
    let mut seen = 0;
    let mut lost = None;
    // Events the daemon had not yet handed to the slow client's queue when it caught up
    // (the fast client saw them first) come after the notice; none of them may be older
    // than what came before it.
    let (mut newest_job, mut after_notice) = (0, 0);
    while let Some(v) = slow.read() {
        match v["type"].as_str() {
            Some("event") => {
                let job = v["job_id"].as_u64().unwrap();
                assert!(job >= newest_job, "an event out of order: {v}");
                newest_job = job;
                match lost {
                    None => seen += 1,
                    Some(_) => after_notice += 1,
                }
            }
            _ => {
                let m = v["error"]["message"]
                    .as_str()
                    .unwrap_or_default()
                    .to_string();
                assert!(lost.is_none(), "a second notice: {m}");
                let n: usize = m
                    .strip_prefix("this client fell behind and lost ")
                    .and_then(|r| r.split(' ').next())
                    .and_then(|n| n.parse().ok())
                    .unwrap_or_else(|| panic!("{m}"));
                lost = Some(n);
            }
        }
    }
    let lost = lost.expect("a notice of the lost events");
    assert!(after_notice < 4, "{after_notice} events after the notice");
    assert_eq!(
        seen + lost + after_notice,
        total,
        "every event seen or counted lost"
    );
    assert!(lost > total / 2, "lost {lost} of {total}");
    // Caught up: the next job's events all arrive.
    slow.w
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    let id = ctl.request(&capture_job(2, 0, "after"))["result"]["job_id"]
        .as_u64()
        .unwrap();
    let after = follow(&mut slow, id);
    // accepted, started, calibration, two steps, finished.
    assert_eq!(after.len(), 6, "{after:?}");
    assert_eq!(follow(&mut fast, id), after);
}

/// `list` over 25 sessions in pages of 10: every session once, newest first; bad limits
/// named; no reply holds every session on disk.
#[test]
fn list_comes_in_pages_that_cover_every_session_once() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(rigd(), dir.path()).start();
    let mut c = d.client();
    c.request(r#"{"kind":"subscribe"}"#);
    let mut ids = Vec::new();
    for _ in 0..25 {
        let id = c.request(&capture_job(1, 0, ""))["result"]["job_id"]
            .as_u64()
            .unwrap();
        follow(&mut c, id);
        ids.push(id);
    }
    let mut before: Option<u64> = None;
    let (mut sessions, mut jobs, mut pages) = (Vec::new(), Vec::new(), 0);
    loop {
        let req = match before {
            Some(b) => format!(r#"{{"kind":"list","limit":10,"before":{b}}}"#),
            None => r#"{"kind":"list","limit":10}"#.to_string(),
        };
        let r = c.request(&req);
        let page = &r["result"];
        let ids_of = |key: &str| -> Vec<u64> {
            page[key]
                .as_array()
                .unwrap()
                .iter()
                .map(|s| s["job_id"].as_u64().unwrap())
                .collect()
        };
        assert!(ids_of("sessions").len() <= 10 && ids_of("jobs").len() <= 10);
        sessions.extend(ids_of("sessions"));
        jobs.extend(ids_of("jobs"));
        pages += 1;
        match page["next_before"].as_u64() {
            Some(b) => before = Some(b),
            None => break,
        }
    }
    ids.reverse();
    assert_eq!(pages, 3);
    assert_eq!(sessions, ids, "newest first, each once");
    assert_eq!(jobs, ids);
    for bad in [0, 1001] {
        let r = c.request(&format!(r#"{{"kind":"list","limit":{bad}}}"#));
        assert_eq!(r["error"]["code"], "bad_request");
        assert_eq!(
            r["error"]["message"],
            format!("`limit` must be 1..=1000, got {bad}")
        );
    }
}

/// `whole_frame` with k = 32 on 1280x720 frames (run, it peaks at 7.5 GB and writes a 947 MB
/// PNG, where the disk check alone budgets ~6.5 MB) is refused at submit naming the estimate
/// and the budget, and so is a replay asking for it.
#[test]
fn a_job_or_replay_over_the_memory_budget_is_refused_before_anything_moves() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn {
        sim: true,
        ..Spawn::new(rigd(), dir.path())
    }
    .start();
    let mut c = d.client();
    let whole = |k: u32| {
        serde_json::json!({"kind": "submit",
            "job": {"steps": 2, "step_um": 50.0, "k": k, "whole_frame": true, "settle_ms": 0}})
        .to_string()
    };
    let r = c.request(&whole(32));
    assert_eq!(r["error"]["code"], "rejected", "{r}");
    let m = r["error"]["message"].as_str().unwrap();
    assert!(m.starts_with("processing this job needs about "), "{m}");
    // 4 k² w h of f32 and its 16-bit copy (6 k² w h, 5.7 GB) while the run ends; then
    // the copy kept, copied again and encoded: a run of it peaks at 7.5 GB (measured).
    let mb: u64 = m["processing this job needs about ".len()..]
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!((7000..8100).contains(&mb), "{m}");
    assert!(
        m.contains("budget of 2048 MB ([daemon] max_job_memory_mb)"),
        "{m}"
    );
    // Nothing was queued.
    let st = c.request(r#"{"kind":"status"}"#);
    assert_eq!(st["result"]["queued"], serde_json::json!([]));
    // A replay of a recorded session asking for the same is refused the same way.
    c.request(r#"{"kind":"subscribe"}"#);
    let r = c.request(
        &serde_json::json!({"kind": "submit",
            "job": {"steps": 2, "step_um": 50.0, "process": false, "settle_ms": 0}})
        .to_string(),
    );
    let id = r["result"]["job_id"].as_u64().unwrap();
    let end = follow(&mut c, id).pop().unwrap();
    let session = end["session"].as_str().unwrap();
    let r = c.request(
        &serde_json::json!({"kind": "replay", "session": session,
            "processing": {"k": 32, "whole_frame": true}})
        .to_string(),
    );
    assert_eq!(r["error"]["code"], "rejected", "{r}");
    let m = r["error"]["message"].as_str().unwrap();
    assert!(
        m.contains("at k = 32 with the whole frame reconstructed"),
        "{m}"
    );
    // k = 4 on the whole frame fits (about 0.3 GB) and is accepted.
    let r = c.request(&whole(4));
    assert_eq!(r["ok"], true, "{r}");
    let _: Value = r;
}

/// Connections that hold a place and say nothing are closed after `idle_timeout_s`;
/// subscribers, who wait for events by design, are not.
#[test]
fn idle_connections_are_closed_and_subscribers_kept() {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn {
        daemon_toml: "idle_timeout_s = 1",
        ..Spawn::new(rigd(), dir.path())
    }
    .start();
    let mut idle = d.client();
    let mut sub = d.client();
    sub.request(r#"{"kind":"subscribe"}"#);
    let t = Instant::now();
    let (lines, closed) = idle.drain(Duration::from_secs(5));
    assert!(closed && lines.is_empty(), "{lines:?}");
    let after = t.elapsed();
    assert!(
        after >= Duration::from_millis(900),
        "closed after {after:?}"
    );
    std::thread::sleep(Duration::from_millis(500));
    let mut ctl = d.client();
    let id = ctl.request(&capture_job(1, 0, ""))["result"]["job_id"]
        .as_u64()
        .unwrap();
    assert_eq!(follow(&mut sub, id).last().unwrap()["event"], "finished");
}
