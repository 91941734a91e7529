//! `rigctl watch JOB`: follow a job's progress until it ends.

use crate::cli::client::{follow, report_end, SocketArg};
use crate::daemon::protocol::Request;

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
    let end = follow(&mut c, a.job_id, total, false)?;
    report_end(a.job_id, &end)
}
