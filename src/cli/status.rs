//! `rigctl status [JOB]`: the daemon's state, or one job's.

use crate::cli::client::SocketArg;
use crate::daemon::protocol::Request;

#[derive(clap::Args, Debug)]
pub struct StatusArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    pub job_id: Option<u64>,
}

pub fn run(a: StatusArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let r = c.request(&Request::Status { job_id: a.job_id })?;
    println!("{}", serde_json::to_string_pretty(&r)?);
    Ok(())
}
