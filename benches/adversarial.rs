//! Resource attacks against the real `rigd` binary, with the figures the goals
//! name: CPU and log lines under a flood of idle connections at a 1024-fd limit, and RSS
//! under pipelined unread `list` requests, subscribers that never read, and a whole-frame
//! k = 32 job. Reads /proc/PID/stat and /proc/PID/status of the child.
//!
//! `cargo bench --bench adversarial` (this build's rigd); `RIGD_BIN=/path/to/rigd` to run
//! the same attacks against another build. The whole-frame attack is only run against this
//! build: a build that accepts it peaks at 7.5 GB.
//! Figures in docs/performance.md.

#[path = "../tests/support/adversary.rs"]
#[allow(dead_code)]
mod adversary;

use adversary::{capture_job, cpu_time, follow, idle_flood, open_fds, rss_kb, Rigd, Spawn};
use std::io::Write;
use std::time::{Duration, Instant};

fn bin() -> (String, bool) {
    match std::env::var("RIGD_BIN") {
        Ok(b) => (b, true),
        Err(_) => (env!("CARGO_BIN_EXE_rigd").to_string(), false),
    }
}

fn mb(kb: u64) -> f64 {
    kb as f64 / 1024.0
}

/// 1100 idle connections for 5 s while a 48x32 job runs, at RLIMIT_NOFILE 1024.
fn flood(bin: &str) {
    adversary::raise_fd_limit(1200);
    let dir = tempfile::tempdir().unwrap();
    let mut d = Spawn {
        nofile: Some(1024),
        ..Spawn::new(bin, dir.path())
    }
    .start();
    let pid = d.pid();
    let mut sub = d.client();
    sub.request(r#"{"kind":"subscribe"}"#);
    let id = sub.request(&capture_job(3000, 5, "flood"))["result"]["job_id"]
        .as_u64()
        .unwrap();
    // The job alone first: what the flood adds is the difference.
    let busy = |secs: u64| {
        let (cpu0, t0) = (cpu_time(pid), Instant::now());
        std::thread::sleep(Duration::from_secs(secs));
        (cpu_time(pid) - cpu0).as_secs_f64() / t0.elapsed().as_secs_f64()
    };
    let alone = busy(5);
    let lines0 = d.log_lines();
    let conns = idle_flood(&d.socket, 1100);
    let cpu = busy(5);
    let fds = open_fds(pid);
    let made = conns.len();
    let lines = d.log_lines() - lines0;
    drop(conns);
    let t = Instant::now();
    let served = loop {
        let mut c = d.client();
        c.w.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
        c.send(r#"{"kind":"hello"}"#);
        if c.read().is_some_and(|r| r["ok"] == true) {
            break t.elapsed();
        }
        if t.elapsed() > Duration::from_secs(30) {
            break t.elapsed();
        }
    };
    // The job as the daemon reports it, on a fresh connection (the subscriber's may be gone).
    let mut c = d.client();
    c.request(&format!(r#"{{"kind":"cancel","job_id":{id}}}"#));
    std::thread::sleep(Duration::from_secs(1));
    let st = c.request(&format!(r#"{{"kind":"status","job_id":{id}}}"#))["result"].clone();
    let end =
        serde_json::json!({"event": st["state"], "reason": st["reason"], "session": st["session"]});
    let steps = std::fs::read_to_string(
        d.data
            .join(end["session"].as_str().unwrap_or("none"))
            .join("steps.csv"),
    )
    .map(|s| s.lines().count().saturating_sub(1))
    .unwrap_or(0);
    drop(sub);
    println!(
        "flood: 1100 idle connections (made {made}), 5 s: CPU {:.1} % of a core ({:.1} % for \
         the job alone before), {lines} log lines, {fds} fds open; a new client served {:.1} ms \
         after they closed; the job {} ({}) with {steps} frames on disk",
        cpu * 100.0,
        alone * 100.0,
        served.as_secs_f64() * 1e3,
        end["event"].as_str().unwrap_or("?"),
        end["reason"].as_str().unwrap_or(""),
    );
    d.stop();
}

/// Sessions with 10 kB labels, then one client pipelines 150 `list` requests and reads none.
fn unread_lists(bin: &str) {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(bin, dir.path()).start();
    let pid = d.pid();
    let mut c = d.client();
    c.request(r#"{"kind":"subscribe"}"#);
    let label = "l".repeat(10_000);
    for _ in 0..100 {
        let id = c.request(&capture_job(1, 0, &label))["result"]["job_id"]
            .as_u64()
            .unwrap();
        follow(&mut c, id);
    }
    let (rss0, _) = rss_kb(pid);
    let greedy = std::os::unix::net::UnixStream::connect(&d.socket).unwrap();
    let mut w = greedy.try_clone().unwrap();
    let one = b"{\"kind\":\"list\"}\n".repeat(150);
    let writer = std::thread::spawn(move || {
        let _ = w.write_all(&one);
    });
    std::thread::sleep(Duration::from_secs(4));
    let (rss1, hwm1) = rss_kb(pid);
    let alive = std::os::unix::net::UnixStream::connect(&d.socket).is_ok();
    drop(greedy);
    let _ = writer.join();
    std::thread::sleep(Duration::from_secs(1));
    let (rss2, _) = rss_kb(pid);
    println!(
        "unread lists: 150 pipelined `list` over 100 sessions of 10 kB labels, never read: RSS \
         {:.0} -> {:.0} MB (peak {:.0} MB), {:.0} MB after the client left; daemon serving: {alive}",
        mb(rss0),
        mb(rss1),
        mb(hwm1),
        mb(rss2)
    );
}

/// 60 subscribers that never read while 200 jobs with 60 kB labels go by.
fn unread_subscribers(bin: &str) {
    let dir = tempfile::tempdir().unwrap();
    let d = Spawn::new(bin, dir.path()).start();
    let pid = d.pid();
    let (rss0, _) = rss_kb(pid);
    let subs: Vec<_> = (0..60)
        .map(|_| {
            let mut s = d.client();
            s.send(r#"{"kind":"subscribe"}"#);
            s
        })
        .collect();
    let mut ctl = d.client();
    let mut fast = d.client();
    fast.request(r#"{"kind":"subscribe"}"#);
    let label = "s".repeat(60_000);
    let t = Instant::now();
    for _ in 0..200 {
        let r = ctl.request(&capture_job(1, 0, &label));
        let id = r["result"]["job_id"].as_u64().unwrap();
        follow(&mut fast, id);
    }
    let took = t.elapsed();
    let (rss1, hwm1) = rss_kb(pid);
    drop(subs);
    std::thread::sleep(Duration::from_secs(2));
    let (rss2, _) = rss_kb(pid);
    println!(
        "unread subscribers: 60 never reading, 200 jobs with 60 kB labels ({:.1} s): RSS {:.0} -> \
         {:.0} MB (peak {:.0} MB), {:.0} MB 2 s after they left",
        took.as_secs_f64(),
        mb(rss0),
        mb(rss1),
        mb(hwm1),
        mb(rss2)
    );
}

/// `whole_frame` at k = 32 on two 1280x720 frames (`rigd --sim`).
fn whole_frame(bin: &str) {
    let dir = tempfile::tempdir().unwrap();
    let d: Rigd = Spawn {
        sim: true,
        ..Spawn::new(bin, dir.path())
    }
    .start();
    let pid = d.pid();
    let (rss0, _) = rss_kb(pid);
    let mut c = d.client();
    let r = c.request(
        r#"{"kind":"submit","job":{"steps":2,"step_um":50,"k":32,"whole_frame":true,"settle_ms":0}}"#,
    );
    std::thread::sleep(Duration::from_secs(1));
    let (rss1, hwm1) = rss_kb(pid);
    println!(
        "whole frame k=32: {}: RSS {:.0} -> {:.0} MB (peak {:.0} MB)",
        match r["ok"].as_bool() {
            Some(true) => "accepted".to_string(),
            _ => format!("refused: {}", r["error"]["message"].as_str().unwrap_or("?")),
        },
        mb(rss0),
        mb(rss1),
        mb(hwm1)
    );
}

fn main() {
    // `cargo bench` passes `--bench`; a filter picks attacks by name.
    let filter: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let (bin, other) = bin();
    println!("rigd: {bin}");
    let run = |name: &str| filter.is_empty() || filter.iter().any(|f| name.contains(f.as_str()));
    if run("flood") {
        flood(&bin);
    }
    if run("lists") {
        unread_lists(&bin);
    }
    if run("subscribers") {
        unread_subscribers(&bin);
    }
    if run("whole_frame") {
        match other {
            true => println!("whole frame k=32: not run against RIGD_BIN (7.5 GB peak)"),
            false => whole_frame(&bin),
        }
    }
}
