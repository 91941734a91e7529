//! `rigctl fetch JOB`: a job's result (and the paper's tables for a study).

use crate::acquisition::study::{tables, StudySummary};
use crate::cli::client::SocketArg;
use crate::daemon::protocol::Request;
use anyhow::Context;

#[derive(clap::Args, Debug)]
pub struct FetchArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// The job whose result to fetch (its id, as `submit` and `list` print it).
    pub job_id: u64,
    /// Write the result JSON here instead of printing it.
    #[arg(long, value_name = "FILE")]
    pub out: Option<std::path::PathBuf>,
    /// Print the study's tables instead of JSON.
    #[arg(long)]
    pub tables: bool,
}

pub fn run(a: FetchArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let r = c.request(&Request::Result { job_id: a.job_id })?;
    if a.tables {
        let s: StudySummary = serde_json::from_value(r["result"]["study"].clone())
            .context("the job's result holds no study")?;
        print!("{}", tables(&s));
        return Ok(());
    }
    let text = serde_json::to_string_pretty(&r)?;
    match a.out {
        Some(p) => std::fs::write(&p, text).with_context(|| format!("writing {}", p.display()))?,
        None => println!("{text}"),
    }
    Ok(())
}
