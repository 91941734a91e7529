//! `rigctl list`: jobs of this daemon run and the sessions on disk, newest first (every
//! page of the daemon's paged `list`).

use crate::cli::client::SocketArg;
use crate::daemon::protocol::{Request, LIST_MAX};

#[derive(clap::Args, Debug)]
pub struct ListArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// Print the reply as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Every page of `list`, newest first: the jobs and the sessions of all pages together.
fn fetch_all(c: &mut crate::cli::client::Client) -> anyhow::Result<serde_json::Value> {
    let (mut jobs, mut sessions) = (Vec::new(), Vec::new());
    let mut before = None;
    loop {
        let r = c.request(&Request::List {
            limit: Some(LIST_MAX),
            before,
        })?;
        let page = |key: &str| r[key].as_array().cloned().unwrap_or_default();
        jobs.extend(page("jobs"));
        sessions.extend(page("sessions"));
        match r["next_before"].as_u64() {
            // Ids fall page after page; one that does not is a daemon bug, not a loop.
            Some(b) if before.is_none_or(|p| b < p) => before = Some(b),
            _ => break,
        }
    }
    Ok(serde_json::json!({"jobs": jobs, "sessions": sessions}))
}

pub fn run(a: ListArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let r = fetch_all(&mut c)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(());
    }
    println!("{:<6} {:<10} {:>13}  session", "job", "state", "frames");
    for j in r["jobs"].as_array().into_iter().flatten() {
        println!(
            "{:<6} {:<10} {:>6}/{:<6}  {}",
            j["job_id"],
            j["state"].as_str().unwrap_or("?"),
            j["frames_done"],
            j["total_frames"],
            j["session"].as_str().unwrap_or("-")
        );
    }
    println!(
        "\n{:<34} {:<11} {:>13}  reason",
        "session", "state", "frames"
    );
    for s in r["sessions"].as_array().into_iter().flatten() {
        println!(
            "{:<34} {:<11} {:>6}/{:<6}  {}",
            s["name"].as_str().unwrap_or("?"),
            s["state"].as_str().unwrap_or("?"),
            s["frames_captured"],
            s["total_frames"],
            s["reason"].as_str().unwrap_or("")
        );
    }
    Ok(())
}
