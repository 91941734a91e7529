//! A PI GCS piezo controller (E-709 style, axis "1") on a pseudo-terminal.
//!
//! Prints the port path, then serves until killed. Example:
//!   sim-gcs --link /tmp/piezo        # then point [piezo] port = "/tmp/piezo" at it

use anyhow::Context;
use clap::Parser;
use rigd_sim::gcs::{GcsSim, GcsSimOptions};
use rigd_sim::motion::{Axis, AxisParams};
use rigd_sim::serve::FaultPlan;
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
    #[arg(long, default_value_t = 0)]
    drop_every: u32,
    #[arg(long, default_value_t = 0)]
    garbage_every: u32,
    /// Make the first move fail halfway (motion error -1024, servo off).
    #[arg(long)]
    alarm_mid_move: bool,
    #[arg(long, default_value_t = 0.0)]
    vanish_every_s: f64,
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
    sim.faults().set(FaultPlan {
        drop_every: a.drop_every,
        garbage_every: a.garbage_every,
        alarm_mid_move: a.alarm_mid_move,
        ..FaultPlan::default()
    });
    println!("{}", sim.path().display());
    loop {
        if a.vanish_every_s > 0.0 {
            std::thread::sleep(Duration::from_secs_f64(a.vanish_every_s));
            sim.faults().vanish();
            eprintln!("port vanished");
            std::thread::sleep(Duration::from_secs(1));
            sim.faults().restore();
            std::thread::sleep(Duration::from_millis(50));
            eprintln!("port back at {}", sim.path().display());
        } else {
            std::thread::sleep(Duration::from_secs(3600));
        }
    }
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
