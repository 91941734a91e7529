//! `rigctl hw`: talk to the configured hardware directly, to bring a rig up and check it
//! before running jobs. Takes the same device locks as rigd (`ownership`, in the
//! config's `[daemon] lock_dir`) for the devices the command opens, so it is refused while
//! a daemon (or another `rigctl hw`) owns them, and names who does.

use crate::config::{Config, StageConfig};
use crate::lock::{lock_dir, Holder, LockFile};
use crate::ownership::{devices_of, lock_devices};
use crate::rig::{open_camera, open_stage, HwError, Stage};
use anyhow::{bail, Context};
use std::path::PathBuf;
use std::time::{Duration, Instant, SystemTime};

#[derive(clap::Args)]
pub struct HwArgs {
    /// The rig's config file.
    #[arg(long, default_value = "/etc/rigd/rigd.toml")]
    pub config: PathBuf,
    /// Address the piezo ([piezo]) instead of the axis ([axis]).
    #[arg(long)]
    pub piezo: bool,
    #[command(subcommand)]
    pub command: HwCommand,
}

#[derive(clap::Subcommand)]
pub enum HwCommand {
    /// Open every configured device and report what answers.
    Probe,
    /// Print the stage's state and reported position.
    Position,
    /// Move by UM micrometres (relative), wait until settled.
    #[command(allow_negative_numbers = true)]
    MoveRel {
        /// The distance to move, µm (negative: towards lower positions).
        #[arg(value_name = "UM")]
        delta_um: f64,
    },
    /// Move to UM micrometres (absolute), wait until settled.
    #[command(allow_negative_numbers = true)]
    MoveAbs {
        /// The position to move to, µm.
        #[arg(value_name = "UM")]
        target_um: f64,
    },
    /// Run the homing cycle.
    Home,
    /// Stop the stage now.
    Stop,
    /// Grab one fresh frame and write it as PNG.
    Grab {
        /// Where to write the frame.
        #[arg(value_name = "OUT.png")]
        out: PathBuf,
    },
    /// List V4L2 capture devices with their formats and sizes.
    Cameras,
    /// Read the configured XL-80 log and summarise it.
    Xl80,
}

pub fn run(args: HwArgs) -> anyhow::Result<()> {
    if let HwCommand::Cameras = args.command {
        return cameras();
    }
    let cfg = Config::load(&args.config)?;
    let section = if args.piezo { "piezo" } else { "axis" };
    let _locks = lock_devices_for(&cfg, &args.command, section)?;
    let stage_cfg = || -> anyhow::Result<_> {
        let purpose = "talk to a stage";
        Ok(if args.piezo {
            cfg.piezo(purpose)?
        } else {
            cfg.axis(purpose)?
        })
    };
    match args.command {
        HwCommand::Probe => probe(&cfg),
        HwCommand::Position => act_and_report(section, stage_cfg()?, "", |_| Ok(())),
        HwCommand::MoveRel { delta_um } => {
            move_and_report(section, stage_cfg()?, |s| s.move_rel(delta_um))
        }
        HwCommand::MoveAbs { target_um } => {
            move_and_report(section, stage_cfg()?, |s| s.move_abs(target_um))
        }
        HwCommand::Home => act_and_report(section, stage_cfg()?, "homed; ", |s| s.home()),
        HwCommand::Stop => act_and_report(section, stage_cfg()?, "stopped; ", |s| s.stop()),
        HwCommand::Grab { out } => grab(&cfg, &out),
        HwCommand::Cameras => unreachable!("handled above"),
        HwCommand::Xl80 => xl80(&cfg),
    }
}

/// Lock the devices `command` opens (a probe: all of them), as rigd does; held until the
/// command is done.
fn lock_devices_for(
    cfg: &Config,
    command: &HwCommand,
    section: &str,
) -> anyhow::Result<Vec<LockFile>> {
    let stage_key = format!("[{section}] port");
    let wanted = |key: &str| match command {
        HwCommand::Probe => true,
        HwCommand::Grab { .. } => key == "[camera] device",
        HwCommand::Cameras | HwCommand::Xl80 => false,
        _ => key == stage_key,
    };
    let devices: Vec<_> = devices_of(cfg)
        .into_iter()
        .filter(|d| wanted(&d.key))
        .collect();
    let me = Holder::me("rigctl hw", None, None);
    let dir = lock_dir(cfg.daemon.lock_dir.as_deref());
    Ok(lock_devices(
        &dir,
        &devices,
        &me,
        ": it owns the hardware (a daemon: stop it first, `sudo systemctl stop rigd`)",
    )?)
}

/// Open the stage, run `act`, print its state and position after.
fn act_and_report(
    section: &str,
    cfg: &StageConfig,
    done: &str,
    act: impl FnOnce(&mut dyn Stage) -> Result<(), HwError>,
) -> anyhow::Result<()> {
    let mut s = open_stage(section, cfg)?;
    act(s.as_mut())?;
    let st = s.status()?;
    println!(
        "{section}: {done}{} at {:.3} µm",
        crate::text::wire_name(&st.state),
        st.position_um
    );
    Ok(())
}

/// Open the stage, `start` a move, wait until it settles, print where it went and how long
/// that took.
fn move_and_report(
    section: &str,
    cfg: &StageConfig,
    start: impl FnOnce(&mut dyn Stage) -> Result<(), HwError>,
) -> anyhow::Result<()> {
    let mut s = open_stage(section, cfg)?;
    let from = s.position_um()?;
    start(s.as_mut())?;
    let t0 = Instant::now();
    let at = s.wait_settled(cfg.move_timeout())?;
    println!(
        "{}: {:.3} -> {:.3} µm (moved {:+.3} µm in {:.2} s)",
        s.name(),
        from,
        at,
        at - from,
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

fn board_path(cfg: &Config) -> Option<PathBuf> {
    cfg.board.as_ref().map(|b| b.path.clone())
}

fn grab(cfg: &Config, out: &std::path::Path) -> anyhow::Result<()> {
    let c = cfg.camera("grab a frame")?;
    let mut cam = open_camera(c, board_path(cfg).as_deref())?;
    let timeout = Duration::from_millis(c.frame_timeout_ms);
    let frame = cam.grab_fresh(SystemTime::now(), timeout)?;
    frame
        .image
        .save_with_format(out, image::ImageFormat::Png)
        .with_context(|| format!("writing {}", out.display()))?;
    let (w, h) = frame.image.dimensions();
    println!(
        "{}: frame {} ({w}x{h}) exposed {} -> {}",
        cam.name(),
        frame.sequence,
        fmt_time(frame.timestamp),
        out.display()
    );
    Ok(())
}

fn fmt_time(t: SystemTime) -> String {
    match t.duration_since(SystemTime::UNIX_EPOCH) {
        Ok(d) => format!("{:.3} s after the epoch", d.as_secs_f64()),
        Err(_) => "before the epoch".into(),
    }
}

fn xl80(cfg: &Config) -> anyhow::Result<()> {
    let x = cfg.xl80("read the interferometer log")?;
    let log = x.read()?;
    println!("{}: {}", x.path.display(), log.summary());
    let m = &log.meta;
    let show = |k: &str, v: Option<String>| {
        if let Some(v) = v {
            println!("  {k}: {v}");
        }
    };
    show("axis", m.axis.clone());
    show("date", m.date.clone());
    show("air temperature", m.air_temp_c.map(|v| format!("{v} °C")));
    show(
        "material temperature",
        m.material_temp_c.map(|v| format!("{v} °C")),
    );
    show("pressure", m.pressure_mbar.map(|v| format!("{v} mbar")));
    show("humidity", m.humidity_pct.map(|v| format!("{v} %")));
    for g in &log.garbled.examples {
        println!("  garbled line {}: {} ({:?})", g.line, g.reason, g.text);
    }
    Ok(())
}

/// Open each configured device; print one line per device; fail if any failed.
fn probe(cfg: &Config) -> anyhow::Result<()> {
    let mut failed = Vec::new();
    let mut report = |what: &str, r: anyhow::Result<String>| match r {
        Ok(s) => println!("{what:7} ok      {s}"),
        Err(e) => {
            println!("{what:7} FAILED  {}", crate::text::error_chain(e.chain()));
            failed.push(what.to_string());
        }
    };
    for (name, sec) in [("axis", &cfg.axis), ("piezo", &cfg.piezo)] {
        match sec {
            None => println!("{name:7} -       no [{name}] section"),
            Some(c) => report(
                name,
                (|| {
                    let mut s = open_stage(name, c)?;
                    let st = s.status()?;
                    Ok(format!(
                        "{} driver on {}: {} at {:.3} µm",
                        crate::text::wire_name(&c.driver),
                        c.port.as_deref().unwrap_or("-"),
                        crate::text::wire_name(&st.state),
                        st.position_um
                    ))
                })(),
            ),
        }
    }
    match &cfg.camera {
        None => println!("camera  -       no [camera] section"),
        Some(c) => report(
            "camera",
            (|| {
                let mut cam = open_camera(c, board_path(cfg).as_deref())?;
                let f = cam.grab(Duration::from_millis(c.frame_timeout_ms))?;
                let (w, h) = f.image.dimensions();
                let px = f.image.as_raw();
                let mean = px.iter().map(|&v| f64::from(v)).sum::<f64>() / px.len().max(1) as f64;
                Ok(format!(
                    "{}: {w}x{h}, frame {}, mean level {mean:.1} DN",
                    cam.name(),
                    f.sequence
                ))
            })(),
        ),
    }
    match &cfg.xl80 {
        None => println!("xl80    -       no [xl80] section"),
        Some(x) if !x.path.exists() => println!(
            "xl80    -       {} does not exist yet (the XL-80 software writes it during a job)",
            x.path.display()
        ),
        Some(x) => report(
            "xl80",
            x.read()
                .map(|l| format!("{}: {}", x.path.display(), l.summary()))
                .map_err(Into::into),
        ),
    }
    if failed.is_empty() {
        Ok(())
    } else {
        bail!("{} failed: {}", failed.len(), failed.join(", "))
    }
}

#[cfg(feature = "v4l2")]
fn cameras() -> anyhow::Result<()> {
    let devs = crate::hw::v4l2::list_devices();
    if devs.is_empty() {
        println!("no V4L2 capture devices (is the camera plugged in? `ls /dev/video*`)");
    }
    for d in devs {
        println!(
            "{}  {}  ({}, {})",
            d.path.display(),
            d.name,
            d.driver,
            d.bus
        );
        for f in d.formats {
            let mark = if f.supported {
                ""
            } else {
                "  (rigd cannot convert)"
            };
            println!(
                "    {} {}{mark}: {}",
                f.fourcc,
                f.description,
                f.sizes.join(", ")
            );
        }
    }
    Ok(())
}

#[cfg(not(feature = "v4l2"))]
fn cameras() -> anyhow::Result<()> {
    bail!("this rigctl was built without V4L2 support: install it with V4L2 support, from the clone: `cargo install --locked --path . --features v4l2` (needs libclang-dev)")
}
