//! `rigd`: the rig daemon. `rigd --config FILE` runs the rig the file describes; `rigd --sim`
//! runs the simulated rig with no configuration.

use anyhow::{bail, Context};
use clap::Parser;
use rigd::config::Config;
use rigd::daemon::hwrig::rig_from_config;
use rigd::daemon::simrig::{sim_rig, Fault, SimSettings};
use rigd::daemon::{default_socket, server, settings_from_config, DaemonSettings};
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "rigd", version, about = "Rig-control and acquisition daemon")]
struct Args {
    /// The rig's TOML configuration.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Run the simulated rig (no hardware, no configuration needed).
    #[arg(long)]
    sim: bool,
    /// Socket path (overrides the configuration).
    #[arg(long, value_name = "PATH")]
    socket: Option<PathBuf>,
    /// Where sessions are written (overrides the configuration; sim default ./rigd-sessions).
    #[arg(long, value_name = "DIR")]
    data_root: Option<PathBuf>,
    /// Inject a fault into the simulated rig: alarm@N, serial-loss@N (N-th move),
    /// camera-timeout@N (N-th grab). Repeatable.
    #[arg(long = "fault", value_name = "KIND@N")]
    faults: Vec<Fault>,
    /// How long a grab waits for a frame on the simulated rig, ms (default 5000; a rig
    /// from --config uses its [camera] frame_timeout_ms).
    #[arg(long, value_name = "MS", value_parser = clap::value_parser!(u64).range(1..))]
    grab_timeout_ms: Option<u64>,
}

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    match run(Args::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("rigd: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(a: Args) -> anyhow::Result<()> {
    let from_config = match &a.config {
        Some(p) => {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            Some(
                settings_from_config(&text, &p.display().to_string())
                    .map_err(anyhow::Error::msg)?,
            )
        }
        None => None,
    };
    if !a.faults.is_empty() && !a.sim {
        bail!("--fault needs --sim");
    }
    if a.grab_timeout_ms.is_some() && !a.sim {
        bail!("--grab-timeout-ms needs --sim (a configured rig uses [camera] frame_timeout_ms)");
    }
    let settings = DaemonSettings {
        socket: a
            .socket
            .or(from_config.as_ref().map(|c| c.socket.clone()))
            .unwrap_or_else(default_socket),
        group: from_config.as_ref().and_then(|c| c.group.clone()),
        data_root: a
            .data_root
            .or(from_config.as_ref().map(|c| c.data_root.clone()))
            .unwrap_or_else(|| PathBuf::from("rigd-sessions")),
    };
    let mut rig = match (&a.config, a.sim) {
        // --sim wins: the config then only sets the daemon's socket and data root.
        (_, true) => sim_rig(&SimSettings {
            faults: a.faults,
            ..SimSettings::default()
        })
        .context("starting the simulated rig")?,
        (Some(p), false) => {
            let cfg = Config::load(p)?;
            rig_from_config(&cfg).with_context(|| format!("opening the rig of {}", p.display()))?
        }
        (None, false) => bail!("give --config FILE for a rig, or --sim for the simulated rig"),
    };
    if let Some(ms) = a.grab_timeout_ms {
        rig.info.grab_timeout_ms = ms;
    }
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(server::run(
        settings,
        rig,
        std::future::pending::<()>(),
        true,
    ))?;
    Ok(())
}
