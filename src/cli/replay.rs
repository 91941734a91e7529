//! `rigctl replay SESSION`: run a recorded session again through the job path.

use crate::cli::client::SocketArg;
use crate::cli::submit::{submit_and_follow, ProcessingArgs};
use crate::daemon::protocol::Request;

#[derive(clap::Args, Debug)]
pub struct ReplayArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// Session name (a folder under the daemon's data root).
    pub session: String,
    /// Processing to use instead of the recorded one.
    #[command(flatten)]
    pub processing: ProcessingArgs,
    /// Return once queued (print the job id) instead of following the job.
    #[arg(long)]
    pub detach: bool,
}

pub fn run(a: ReplayArgs) -> anyhow::Result<()> {
    let req = Request::Replay {
        session: a.session.clone(),
        processing: a.processing.processing(),
    };
    submit_and_follow(&a.socket, req, a.detach).map(|_| ())
}
