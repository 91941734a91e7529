//! `rigctl pause JOB`, `rigctl resume JOB|SESSION`: pause a running job at its next step
//! boundary, let it go on; a session name (not a number) resumes an interrupted or failed
//! session as a new job capturing its missing frames (`resume_session`).

use crate::cli::client::SocketArg;
use crate::daemon::protocol::{Request, SubmitReply};

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
    /// A paused job's id, or the name of an interrupted or failed session to complete.
    #[arg(value_name = "JOB|SESSION")]
    pub what: String,
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
    if let Ok(job_id) = a.what.parse::<u64>() {
        c.request(&Request::Resume { job_id })?;
        println!("job {job_id}: resumed");
        return Ok(());
    }
    let r: SubmitReply = serde_json::from_value(c.request(&Request::ResumeSession {
        session: a.what.clone(),
    })?)?;
    println!(
        "job {}: resumes session {} ({} missing frames)",
        r.job_id, a.what, r.total_frames
    );
    Ok(())
}
