//! `rigd`: the rig daemon. `rigd --config FILE` runs the rig the file describes; `rigd --sim`
//! runs the simulated rig with no configuration.

use anyhow::{bail, Context};
use clap::Parser;
use rigd::config::{Config, DaemonSettings};
use rigd::daemon::{notify, server};
use rigd::ownership::{devices_of, Device, Ownership};
use rigd::rig::Rig;
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "rigd", version, about = "Rig-control and acquisition daemon")]
struct Args {
    /// The rig's TOML configuration.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Run the simulated rig (no hardware, no configuration needed).
    #[cfg(feature = "sim")]
    #[arg(long)]
    sim: bool,
    /// Socket path (overrides the configuration).
    #[arg(long, value_name = "PATH")]
    socket: Option<PathBuf>,
    /// Where sessions are written (overrides the configuration; sim default ./rigd-sessions).
    #[arg(long, value_name = "DIR")]
    data_root: Option<PathBuf>,
    /// The simulated rig's camera profile: ideal (default), webcam or stress (docs/sim.md).
    #[cfg(feature = "sim")]
    #[arg(long, value_name = "PROFILE")]
    camera: Option<String>,
    /// Inject a fault into the simulated rig: alarm@N, serial-loss@N (N-th move),
    /// camera-timeout@N (N-th grab), panic@N (the N-th move panics). Repeatable.
    #[cfg(feature = "sim")]
    #[arg(long = "fault", value_name = "KIND@N")]
    faults: Vec<rigd::rig::Fault>,
    /// How long a grab waits for a frame on the simulated rig, ms (default 5000; a rig
    /// from --config uses its [camera] frame_timeout_ms).
    #[cfg(feature = "sim")]
    #[arg(long, value_name = "MS", value_parser = clap::value_parser!(u64).range(1..))]
    grab_timeout_ms: Option<u64>,
}

fn main() -> std::process::ExitCode {
    use std::io::IsTerminal;
    // Colours only for a person at a terminal: journald and log files get plain text.
    let ansi = std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_ansi(ansi)
        .with_writer(std::io::stderr)
        .init();
    match run(Args::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("rigd: {}", rigd::text::error_chain(e.chain()));
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(a: Args) -> anyhow::Result<()> {
    // The config is read once: its [daemon] settings under the command line's, and its rig.
    let cfg = a.config.as_ref().map(Config::load).transpose()?;
    let file = cfg.as_ref().map(|c| c.daemon.clone()).unwrap_or_default();
    let mut settings: DaemonSettings = file.overridden(a.socket.clone(), a.data_root.clone());
    // Reported to clients (hello, paths of sessions): absolute, whatever the daemon's cwd.
    settings.data_root = std::path::absolute(&settings.data_root)
        .with_context(|| format!("data root {}", settings.data_root.display()))?;
    // Everything this daemon will own is claimed before the first byte to a controller and
    // before recovery touches a session: a second instance stops here, having changed nothing.
    let owner = Ownership::claim(&settings, &devices(&a, cfg.as_ref()), "rigd")?;
    let rig = open_rig(&a, cfg.as_ref())?;
    let rt = tokio::runtime::Runtime::new()?;
    let rig = rt.block_on(server::run(
        &owner,
        rig,
        std::future::pending::<()>(),
        true,
        || notify::notify("READY=1"),
    ))?;
    // The ports close before the locks are released.
    drop(rig);
    drop(owner);
    Ok(())
}

/// The devices the rig will open: none for `--sim` (its emulators are its own), else the
/// config's.
fn devices(a: &Args, cfg: Option<&Config>) -> Vec<Device> {
    #[cfg(feature = "sim")]
    if a.sim {
        return Vec::new();
    }
    let _ = a;
    cfg.map(devices_of).unwrap_or_default()
}

/// The rig to serve: `--sim`'s (the config then only sets the daemon's socket and data
/// root), else the config's.
#[cfg(feature = "sim")]
fn open_rig(a: &Args, cfg: Option<&Config>) -> anyhow::Result<Rig> {
    if !a.faults.is_empty() && !a.sim {
        bail!("--fault needs --sim");
    }
    if a.camera.is_some() && !a.sim {
        bail!("--camera needs --sim (a configured rig's camera is its [camera] section)");
    }
    if a.grab_timeout_ms.is_some() && !a.sim {
        bail!("--grab-timeout-ms needs --sim (a configured rig uses [camera] frame_timeout_ms)");
    }
    if !a.sim {
        return config_rig(cfg);
    }
    let profile = a.camera.as_deref().unwrap_or("ideal");
    let settings = rigd::rig::SimSettings {
        faults: a.faults.clone(),
        ..rigd::rig::SimSettings::for_camera(profile)
            .with_context(|| format!("--camera {profile}"))?
    };
    let mut rig = rigd::rig::simulated(&settings).context("starting the simulated rig")?;
    if let Some(ms) = a.grab_timeout_ms {
        rig.info.grab_timeout_ms = ms;
    }
    Ok(rig)
}

#[cfg(not(feature = "sim"))]
fn open_rig(_a: &Args, cfg: Option<&Config>) -> anyhow::Result<Rig> {
    config_rig(cfg)
}

fn config_rig(cfg: Option<&Config>) -> anyhow::Result<Rig> {
    let Some(cfg) = cfg else {
        if cfg!(feature = "sim") {
            bail!("give --config FILE for a rig, or --sim for the simulated rig");
        }
        bail!("give --config FILE for a rig (this rigd was built without the `sim` feature: no --sim)");
    };
    rigd::rig::from_config(cfg)
        .with_context(|| format!("opening the rig of {}", cfg.source.display()))
}
