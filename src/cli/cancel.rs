//! `rigctl cancel JOB`: cancel a queued job, or stop a running one after its current step.

use crate::cli::client::SocketArg;
use crate::daemon::protocol::Request;

#[derive(clap::Args, Debug)]
pub struct CancelArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// The job to cancel (its id, as `submit` and `list` print it).
    pub job_id: u64,
}

pub fn run(a: CancelArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let r = c.request(&Request::Cancel { job_id: a.job_id })?;
    println!("job {}: {}", a.job_id, r["state"].as_str().unwrap_or("?"));
    Ok(())
}
