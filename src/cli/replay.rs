//! `rigctl replay SESSION`: run a recorded session again through the job path.

use crate::cli::client::SocketArg;
use crate::cli::submit::{submit_and_follow, CombineArg, EstimatorArg, RegistrationArg};
use crate::daemon::protocol::{ProcessingOverride, Request};

#[derive(clap::Args, Debug)]
pub struct ReplayArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// Session name (a folder under the daemon's data root).
    pub session: String,
    #[arg(long)]
    pub k: Option<u32>,
    #[arg(long, value_enum)]
    pub estimator: Option<EstimatorArg>,
    #[arg(long, value_enum)]
    pub combine: Option<CombineArg>,
    #[arg(long, value_enum)]
    pub registration: Option<RegistrationArg>,
    #[arg(long)]
    pub detach: bool,
}

pub fn run(a: ReplayArgs) -> anyhow::Result<()> {
    let req = Request::Replay {
        session: a.session.clone(),
        processing: ProcessingOverride {
            registration: a.registration.map(Into::into),
            k: a.k,
            estimator: a.estimator.map(Into::into),
            combine: a.combine.map(Into::into),
        },
    };
    submit_and_follow(&a.socket, req, a.detach).map(|_| ())
}
