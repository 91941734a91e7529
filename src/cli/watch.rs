//! `rigctl watch JOB`: follow a job's progress until it ends.

use crate::cli::client::{follow_from, report_end, Pace, SocketArg};
use crate::daemon::protocol::Request;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct WatchArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// The job to follow (its id, as `submit` and `list` print it).
    pub job_id: u64,
}

pub fn run(a: WatchArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let r = c.request(&Request::Subscribe {
        job_id: Some(a.job_id),
    })?;
    let st = &r["status"];
    if let Some(s @ ("finished" | "failed" | "cancelled")) = st["state"].as_str() {
        println!(
            "job {} already {s}{}",
            a.job_id,
            st["reason"]
                .as_str()
                .map(|r| format!(": {r}"))
                .unwrap_or_default()
        );
        return Ok(());
    }
    let total = st["total_frames"].as_u64().unwrap_or_default() as u32;
    let done = st["frames_done"].as_u64().unwrap_or_default() as u32;
    // Frames done before we attached took the job's elapsed time, not none.
    let pace = match st["elapsed_s"].as_f64() {
        Some(e) => Pace::running_for(e, Instant::now()),
        None => Pace::default(),
    };
    let end = follow_from(&mut c, a.job_id, total, false, pace, done)?;
    report_end(a.job_id, &end)?;
    crate::cli::submit::print_results(&mut c, a.job_id)
}
