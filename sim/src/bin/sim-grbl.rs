//! A GRBL 1.1 controller on a pseudo-terminal, for pointing rigd (or any G-code sender) at.
//!
//! Prints the port path, then serves until killed. Example:
//!   sim-grbl --link /tmp/grbl        # then: rigctl hw --config ... with port = "/tmp/grbl"

use anyhow::Context;
use clap::Parser;
use rigd_sim::grbl::{GrblSim, GrblSimOptions};
use rigd_sim::motion::{Axis, AxisParams};
use rigd_sim::serve::FaultPlan;
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
    /// Drop every Nth reply (0 = never).
    #[arg(long, default_value_t = 0)]
    drop_every: u32,
    /// A garbage line before every Nth reply (0 = never).
    #[arg(long, default_value_t = 0)]
    garbage_every: u32,
    /// Interrupt the first move halfway with ALARM:1.
    #[arg(long)]
    alarm_mid_move: bool,
    /// Make the port vanish every N seconds, for a second (0 = never).
    #[arg(long, default_value_t = 0.0)]
    vanish_every_s: f64,
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
        ..GrblSimOptions::default()
    };
    let sim = GrblSim::spawn(axis, opts, a.link.as_deref()).context("opening a pty")?;
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
