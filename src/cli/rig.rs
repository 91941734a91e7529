//! `rigctl unlock | home | reconnect [--stage axis|piezo]`: clear a rig fault through the
//! daemon (which runs the request on the rig between jobs), and print the rig state after.

use crate::acquisition::StageKind;
use crate::cli::client::SocketArg;
use crate::daemon::protocol::{Request, RigActionReply};
use crate::daemon::protocol::{RigAction, RigState};

#[derive(clap::Args, Debug)]
pub struct RigArgs {
    #[command(flatten)]
    pub socket: SocketArg,
    /// The stage (default: the stage in fault, else the axis).
    #[arg(long, value_enum)]
    pub stage: Option<StageKind>,
}

pub fn run(action: RigAction, a: RigArgs) -> anyhow::Result<()> {
    let mut c = a.socket.connect()?;
    let stage = a.stage;
    let req = match action {
        RigAction::Unlock => Request::Unlock { stage },
        RigAction::Home => Request::Home { stage },
        RigAction::Reconnect => Request::Reconnect { stage },
        other => anyhow::bail!("`{}` is not a fault-clearing request", other.name()),
    };
    let r: RigActionReply = serde_json::from_value(c.request(&req)?)?;
    println!(
        "{} {}: {} at {:.3} µm; rig {}",
        r.stage,
        r.request.name(),
        crate::text::wire_name(&r.state),
        r.position_um,
        describe(&r.rig_state)
    );
    Ok(())
}

/// One line for a rig state.
pub fn describe(s: &RigState) -> String {
    match s {
        RigState::Ready => "ready".into(),
        RigState::Busy {
            job_id: Some(id), ..
        } => format!("busy (job {id})"),
        RigState::Busy {
            request, waiting, ..
        } => format!(
            "busy ({}{})",
            request.map_or("a request", |r| r.name()),
            waiting.map_or(String::new(), |n| format!(", {n} waiting"))
        ),
        RigState::Fault(f) => format!("in fault: {}", f.refusal()),
    }
}
