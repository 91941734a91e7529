//! `rigctl pause JOB`, `rigctl resume JOB`: pause a running job at its next step boundary,
//! let it go on. `rigctl resume SESSION`: resume an interrupted session as a new job
//! (`resume_session`), followed as `submit` follows a job.

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
    /// A paused job's id (it goes on with its next frame), or an incomplete, failed or
    /// cancelled session's name (a new job takes its plan on from its first missing frame).
    #[arg(value_name = "JOB|SESSION")]
    pub target: String,
    /// A session: return once queued (print the job id) instead of following the job.
    #[arg(long)]
    pub detach: bool,
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
    // Session names start with a UTC stamp and hold a `-`: never a bare number.
    let Ok(job_id) = a.target.parse::<u64>() else {
        let req = Request::ResumeSession {
            session: a.target.clone(),
        };
        return crate::cli::submit::submit_and_follow(&a.socket, req, a.detach).map(|_| ());
    };
    if a.detach {
        anyhow::bail!("--detach is for resuming a session; job {job_id} resumes in place");
    }
    let mut c = a.socket.connect()?;
    c.request(&Request::Resume { job_id })?;
    println!("job {job_id}: resumed");
    Ok(())
}
