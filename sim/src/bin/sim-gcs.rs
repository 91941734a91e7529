//! A PI GCS piezo controller (E-709 style, axis "1") on a pseudo-terminal.
//!
//! Prints the port path, then serves until killed. Example:
//!   sim-gcs --link /tmp/piezo        # then point [piezo] port = "/tmp/piezo" at it

use anyhow::Context;
use clap::Parser;
use rigd_sim::gcs::{GcsSim, GcsSimOptions};
use rigd_sim::motion::{Axis, AxisParams};
use rigd_sim::serve::FaultArgs;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

#[derive(Parser)]
#[command(about = "Serve a simulated PI GCS piezo controller on a pseudo-terminal")]
struct Args {
    /// Also make this stable symlink to the pty (it survives --vanish-every-s).
    #[arg(long)]
    link: Option<PathBuf>,
    /// Closed-loop settling time after a move, ms.
    #[arg(long, default_value_t = 10)]
    settle_ms: u64,
    /// µm per GCS position unit.
    #[arg(long, default_value_t = 1.0)]
    um_per_unit: f64,
    /// Travel range of the flexure, µm.
    #[arg(long, default_value_t = 0.0)]
    min_um: f64,
    #[arg(long, default_value_t = 100.0)]
    max_um: f64,
    #[arg(long, default_value_t = 0.005)]
    position_error_rms_um: f64,
    /// Servo on at power-on.
    #[arg(long)]
    servo_on: bool,
    #[command(flatten)]
    faults: FaultArgs,
}

fn main() -> anyhow::Result<()> {
    let a = Args::parse();
    let axis = Arc::new(Axis::new(piezo_params(&a)));
    let opts = GcsSimOptions {
        settle: Duration::from_millis(a.settle_ms),
        um_per_unit: a.um_per_unit,
        servo_on_at_boot: a.servo_on,
        ..GcsSimOptions::default()
    };
    let sim = GcsSim::spawn(axis, opts, a.link.as_deref()).context("opening a pty")?;
    a.faults.serve_forever(sim.faults(), || sim.path())
}

/// A flexure: short travel, fast, nanometre-level positioning.
fn piezo_params(a: &Args) -> AxisParams {
    AxisParams {
        max_speed_um_s: 10_000.0,
        accel_um_s2: 1_000_000.0,
        position_error_rms_um: a.position_error_rms_um,
        hard_min_um: a.min_um,
        hard_max_um: a.max_um,
        ..AxisParams::default()
    }
}
