//! The `rigctl` command line: one module per subcommand, wired here.

pub mod calibrate;
pub mod cancel;
pub mod client;
#[cfg(feature = "sim")]
pub mod demo;
pub mod export;
pub mod fetch;
pub mod hw;
pub mod index;
pub mod info;
pub mod interrupt;
pub mod list;
pub mod manual;
pub mod pause;
pub mod plan_args;
pub mod process;
pub mod replay;
pub mod report;
pub mod reprocess;
pub mod results;
pub mod rig;
pub mod schema;
pub mod server_line;
pub mod status;
pub mod submit;
pub mod view;
pub mod watch;
pub mod web;

use crate::daemon::protocol::RigAction;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "rigctl",
    version,
    about = "Control a rigd metrology rig, or process frames offline"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand)]
pub enum Command {
    /// Run the paper's study on a simulated rig through a temporary daemon, print Tables 1-3.
    #[cfg(feature = "sim")]
    Demo(demo::DemoArgs),
    /// Queue a capture job and follow it.
    Submit(submit::SubmitArgs),
    /// Follow a job until it ends.
    Watch(watch::WatchArgs),
    /// The daemon's state, or one job's.
    Status(status::StatusArgs),
    /// The rig the daemon runs: mode, scale, frame size, limits, the axis controller's
    /// settings, data root, versions.
    #[command(alias = "hello")]
    Info(info::InfoArgs),
    /// Cancel a job.
    Cancel(cancel::CancelArgs),
    /// Jobs and sessions.
    List(list::ListArgs),
    /// A job's result.
    Fetch(fetch::FetchArgs),
    /// Run a recorded session again, optionally with other processing settings.
    Replay(replay::ReplayArgs),
    /// Write a recorded session as OME-Zarr, OME-TIFF or NeXus/HDF5 (feature `hdf5`) with
    /// its units, positions and times, offline.
    Export(export::ExportArgs),
    /// Fit a calibration (local scale per target, field model) from a folder scan of known
    /// displacements (frames/*.png + steps.csv).
    Calibrate(calibrate::CalibrateArgs),
    /// Measure target offsets offline: a session run by run as the daemon did, or a folder
    /// of frames (frames/*.png + steps.csv).
    Process(process::ProcessArgs),
    /// Write a processed session's figures (Figures 4 and 5, per-step residuals) and report.
    Report(report::ReportArgs),
    /// Process many sessions again without a daemon, into each one's processed/<settings>/.
    Reprocess(reprocess::ReprocessArgs),
    /// Query the results index (<data root>/index.sqlite) to CSV on stdout.
    Results(index::ResultsArgs),
    /// Rebuild the results index from the sessions, or merge indexes.
    Index(index::IndexArgs),
    /// Talk to the configured hardware directly (bring-up; only when no daemon holds it).
    Hw(hw::HwArgs),
    /// Clear a latched alarm through the daemon (GRBL `$X`; GCS `ERR?` and servo on).
    Unlock(rig::RigArgs),
    /// Home a stage through the daemon (GRBL `$H`; GCS `FRF` or a move to home_um).
    Home(rig::RigArgs),
    /// Close and reopen a stage's port through the daemon (after the port was lost).
    Reconnect(rig::RigArgs),
    /// Print the protocol's JSON Schema (docs/protocol.schema.json).
    Schema(schema::SchemaArgs),
    /// One fresh frame (a running job's next one) with the targets in it, saved as PNG.
    Snap(view::SnapArgs),
    /// The live view: targets, their centres and sharpness, refreshed; the latest PNG kept.
    View(view::ViewArgs),
    /// Both stages' positions as the controllers report them.
    Position(manual::PositionArgs),
    /// Move a stage when no job runs (`--to-um X` absolute, `--by-um D` relative).
    Move(manual::MoveArgs),
    /// Jog a stage from the keyboard (or keys on stdin), showing its position.
    Jog(manual::JogArgs),
    /// Stop a manual move under way.
    Stop(manual::StopArgs),
    /// Pause a running job at its next step boundary.
    Pause(pause::PauseArgs),
    /// Let a paused job go on with its next frame; or resume an interrupted session from
    /// its first missing frame as a new job.
    Resume(pause::ResumeArgs),
    /// The browser console: serve the rig's page on 127.0.0.1, printing its URL with a
    /// fresh access token (docs/console.md).
    Web(web::WebArgs),
}

/// Entry point of the `rigctl` binary.
/// `rigctl`: run [`main`] and say how it ended. A reader of stdout that went away
/// (`rigctl list | head`) ends it quietly and successfully: `println!`'s panic on the
/// closed pipe, and an error that is stdout's EPIPE, are not rigctl's failures. (SIGPIPE
/// stays ignored, as Rust sets it: the daemon's socket closing is an error to report.)
pub fn run() -> std::process::ExitCode {
    use std::process::ExitCode;
    let hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        if !stdout_gone(info.payload()) {
            hook(info)
        }
    }));
    match std::panic::catch_unwind(main) {
        Ok(Ok(())) => ExitCode::SUCCESS,
        Ok(Err(e)) if is_broken_pipe(&e) && stdout_closed() => ExitCode::SUCCESS,
        Ok(Err(e)) => {
            eprintln!("rigctl: {}", crate::text::error_chain(e.chain()));
            ExitCode::FAILURE
        }
        Err(p) if stdout_gone(p.as_ref()) => ExitCode::SUCCESS,
        Err(p) => std::panic::resume_unwind(p),
    }
}

/// A panic of `print!`/`println!` on a closed stdout.
fn stdout_gone(payload: &(dyn std::any::Any + Send)) -> bool {
    let m = crate::text::panic_message(payload);
    m.starts_with("failed printing to stdout") && m.contains("os error 32")
}

fn is_broken_pipe(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.downcast_ref::<std::io::Error>()
            .is_some_and(|io| io.kind() == std::io::ErrorKind::BrokenPipe)
    })
}

/// Whether stdout is a pipe whose reader has gone (poll says POLLERR).
fn stdout_closed() -> bool {
    let mut p = libc::pollfd {
        fd: libc::STDOUT_FILENO,
        events: libc::POLLOUT,
        revents: 0,
    };
    // SAFETY: one valid pollfd, no timeout.
    let n = unsafe { libc::poll(&mut p, 1, 0) };
    n == 1 && p.revents & libc::POLLERR != 0
}

pub fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        #[cfg(feature = "sim")]
        Command::Demo(a) => demo::run(a),
        Command::Submit(a) => submit::run(a),
        Command::Watch(a) => watch::run(a),
        Command::Status(a) => status::run(a),
        Command::Info(a) => info::run(a),
        Command::Cancel(a) => cancel::run(a),
        Command::List(a) => list::run(a),
        Command::Fetch(a) => fetch::run(a),
        Command::Replay(a) => replay::run(a),
        Command::Export(a) => export::run(a),
        Command::Calibrate(a) => calibrate::run(a),
        Command::Process(a) => process::run(a),
        Command::Report(a) => report::run(a),
        Command::Reprocess(a) => reprocess::run(a),
        Command::Results(a) => index::results(a),
        Command::Index(a) => index::run(a),
        Command::Hw(a) => hw::run(a),
        Command::Unlock(a) => rig::run(RigAction::Unlock, a),
        Command::Home(a) => rig::run(RigAction::Home, a),
        Command::Reconnect(a) => rig::run(RigAction::Reconnect, a),
        Command::Schema(a) => schema::run(a),
        Command::Snap(a) => view::snap(a),
        Command::View(a) => view::view(a),
        Command::Position(a) => manual::position(a),
        Command::Move(a) => manual::move_stage(a),
        Command::Jog(a) => manual::jog(a),
        Command::Stop(a) => manual::stop(a),
        Command::Pause(a) => pause::pause(a),
        Command::Resume(a) => pause::resume(a),
        Command::Web(a) => web::run(a),
    }
}
