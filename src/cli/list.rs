//! `rigctl list`: jobs of this daemon run and the sessions on disk.

use crate::cli::client::SocketArg;
use crate::daemon::protocol::Request;

#[derive(clap::Args, Debug)]
pub struct ListArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// Print the reply as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: ListArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let r = c.request(&Request::List)?;
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
