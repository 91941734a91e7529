//! `rigctl status [JOB]`: the daemon's state (the rig, the running job, the queue), or one
//! job's, as tables; `--json` for machines.

use crate::cli::client::SocketArg;
use crate::cli::list::jobs_table;
use crate::cli::rig::describe;
use crate::daemon::protocol::JobStatus;
use crate::daemon::protocol::{DaemonStatus, Request};

#[derive(clap::Args, Debug)]
pub struct StatusArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// One job's status (its id, as `submit` and `list` print it); without it, the daemon's.
    pub job_id: Option<u64>,
    /// Print the reply as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: StatusArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let r = c.request(&Request::Status { job_id: a.job_id })?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(());
    }
    print!(
        "{}",
        match a.job_id {
            Some(_) => job_text(&serde_json::from_value(r)?),
            None => daemon_text(&serde_json::from_value(r)?),
        }
    );
    Ok(())
}

/// One job: its table row, and why it ended if it did not finish.
pub fn job_text(j: &JobStatus) -> String {
    let mut s = jobs_table(std::slice::from_ref(j)).render();
    if let Some(r) = &j.reason {
        s.push_str(&format!("reason: {r}\n"));
    }
    s
}

/// The daemon: the rig's state, then the running and queued jobs.
pub fn daemon_text(d: &DaemonStatus) -> String {
    let mut s = format!("rig: {}\n", describe(&d.rig_state));
    if d.shutting_down {
        s.push_str("the daemon is shutting down\n");
    }
    let jobs: Vec<JobStatus> = d.running.iter().chain(&d.queued_jobs).cloned().collect();
    match jobs.is_empty() {
        true => s.push_str("no job running or queued\n"),
        false => s.push_str(&jobs_table(&jobs).render()),
    }
    s
}
