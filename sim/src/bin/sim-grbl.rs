//! A GRBL 1.1 controller on a pseudo-terminal, for pointing rigd (or any G-code sender) at.
//!
//! Prints the port path, then serves until killed. Example:
//!   sim-grbl --link /tmp/grbl        # then: rigctl hw --config ... with port = "/tmp/grbl"

use anyhow::Context;
use clap::Parser;
use rigd_sim::grbl::{GrblSim, GrblSimOptions};
use rigd_sim::motion::{Axis, AxisParams};
use rigd_sim::serve::FaultArgs;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

#[derive(Parser)]
#[command(about = "Serve a simulated GRBL 1.1 axis on a pseudo-terminal")]
struct Args {
    /// Also make this stable symlink to the pty (it survives --vanish-every-s).
    #[arg(long)]
    link: Option<PathBuf>,
    /// Boot delay between the port opening and the banner, ms (a real Arduino: ~1500).
    #[arg(long, default_value_t = 200)]
    boot_ms: u64,
    /// Start (and stay after reset) in Alarm until '$H' or '$X', as with homing enabled.
    #[arg(long)]
    alarm_on_boot: bool,
    /// Opening the port does not reset the board (no banner until a soft reset).
    #[arg(long)]
    no_reset_on_open: bool,
    #[arg(long, default_value_t = 20_000.0)]
    max_speed_um_s: f64,
    #[arg(long, default_value_t = 500_000.0)]
    accel_um_s2: f64,
    #[arg(long, default_value_t = 2.0)]
    position_error_rms_um: f64,
    #[arg(long, default_value_t = -5_000.0)]
    hard_min_um: f64,
    #[arg(long, default_value_t = 300_000.0)]
    hard_max_um: f64,
    #[command(flatten)]
    faults: FaultArgs,
}

fn main() -> anyhow::Result<()> {
    let a = Args::parse();
    let axis = Arc::new(Axis::new(AxisParams {
        max_speed_um_s: a.max_speed_um_s,
        accel_um_s2: a.accel_um_s2,
        position_error_rms_um: a.position_error_rms_um,
        hard_min_um: a.hard_min_um,
        hard_max_um: a.hard_max_um,
        ..AxisParams::default()
    }));
    let opts = GrblSimOptions {
        boot_delay: Duration::from_millis(a.boot_ms),
        alarm_on_boot: a.alarm_on_boot,
        reset_on_open: !a.no_reset_on_open,
        ..GrblSimOptions::default()
    };
    let sim = GrblSim::spawn(axis, opts, a.link.as_deref()).context("opening a pty")?;
    a.faults.serve_forever(sim.faults(), || sim.path())
}
