//! Capture overhead on `rigd --sim`'s rig (goal: ≤ 5 % of a step): a 40-frame job at 50 µm steps,
//! settle 20 ms, processed at k = 10. From the session's steps.csv: the median interval
//! between frames' exposure times against the median move + settle + grab. What is left is
//! the engine's own time per step; the frame's PNG, fsync and processing run behind it.
//!
//! `cargo bench --bench capture_overhead` (figures in docs/performance.md).

#[path = "support/job.rs"]
mod support;

use rigd::cli::client::Client;
use rigd::config::DaemonSettings;
use rigd::daemon::protocol::Request;
use rigd::daemon::server::Background;
use rigd::rig::{simulated, SimSettings};

const JOBS: usize = 5;

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// One job; (median interval, median move + settle + grab), ms.
fn one_job(c: &mut Client, data: &std::path::Path) -> (f64, f64) {
    let (_, s, mut intervals) = support::forty_frames(c, data);
    let mut busy: Vec<f64> = s
        .steps
        .iter()
        .skip(1)
        .map(|r| r.move_ms + r.settle_ms + r.grab_ms)
        .collect();
    (median(&mut intervals), median(&mut busy))
}

fn main() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let settings = DaemonSettings {
        socket: dir.path().join("rigd.sock"),
        group: None,
        data_root: data.clone(),
        ..DaemonSettings::default()
    };
    let rig = simulated(&SimSettings::default()).unwrap();
    let _bg = Background::start(settings, rig).unwrap();
    let mut c = Client::connect(&dir.path().join("rigd.sock")).unwrap();
    c.request(&Request::Subscribe { job_id: None }).unwrap();
    println!("capture overhead, rigd --sim rig, 40 frames at 50 µm, settle 20 ms, k = 10");
    println!("job  interval_ms  move+settle+grab_ms  overhead_ms  overhead_%");
    let mut overheads = Vec::new();
    for j in 0..JOBS {
        let (interval, busy) = one_job(&mut c, &data);
        let pct = 100.0 * (interval - busy) / interval;
        overheads.push(pct);
        println!(
            "{j:>3}  {interval:>11.1}  {busy:>19.1}  {:>11.1}  {pct:>10.1}",
            interval - busy
        );
    }
    println!(
        "median overhead: {:.1} % of the step interval",
        median(&mut overheads)
    );
}
