//! `rigctl pause JOB`, `rigctl resume JOB`: pause a running job at its next step boundary,
//! let it go on.

use crate::cli::client::SocketArg;
use crate::daemon::protocol::Request;

#[derive(clap::Args, Debug)]
pub struct PauseArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// The running job to pause.
    pub job_id: u64,
}

#[derive(clap::Args, Debug)]
pub struct ResumeArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// The paused job to resume.
    pub job_id: u64,
}

pub fn pause(a: PauseArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let r = c.request(&Request::Pause { job_id: a.job_id })?;
    match r["state"].as_str() {
        Some("pausing") => println!("job {}: pausing at its next step boundary", a.job_id),
        Some(s) => println!("job {}: {s}", a.job_id),
        None => println!("job {}: ?", a.job_id),
    }
    Ok(())
}

pub fn resume(a: ResumeArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    c.request(&Request::Resume { job_id: a.job_id })?;
    println!("job {}: resumed", a.job_id);
    Ok(())
}
