//! sim-session: render a session folder for `rigctl process` on the simulated rig.
//!
//! `frames/0000.png ...` (8-bit RGB), `steps.csv` (`index,position_um`: the commanded
//! positions), an XL-80 log of the same motion (`xl80.csv` and/or `xl80.rtx`) and the sim
//! config used (`sim.toml`). The motion runs on a virtual clock (no waiting): at each step
//! the axis moves with its trapezoidal profile to the commanded position plus its random
//! positioning error, dwells, and the frame is exposed mid-dwell.

use anyhow::{bail, Context, Result};
use clap::{Parser, ValueEnum};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rigd_sim::motion::{AxisParams, Leadscrew, Profile, TruePosition};
use rigd_sim::xl80::{write_log, LogFormat, Xl80};
use rigd_sim::{FrameRenderer, SimRigConfig};
use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant, SystemTime};

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Xl80Out {
    Csv,
    Rtx,
    Both,
    None,
}

#[derive(Parser)]
#[command(
    name = "sim-session",
    about = "Render a session folder (frames/*.png, steps.csv, XL-80 log) on the simulated rig"
)]
struct Args {
    /// Output folder (created; must not hold a session already).
    #[arg(long)]
    out: PathBuf,
    /// Number of frames (steps).
    #[arg(long, default_value_t = 20)]
    frames: usize,
    /// Step between frames, µm.
    #[arg(long, default_value_t = 50.0)]
    step_um: f64,
    /// Axis position of the first frame, µm.
    #[arg(long, default_value_t = 0.0)]
    start_um: f64,
    /// Seed of the camera effects and of the axis' positioning errors.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Sim rig config (TOML, `SimRigConfig`): camera, board, axis, XL-80. Defaults otherwise.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Board file, overriding the config's.
    #[arg(long)]
    board: Option<PathBuf>,
    /// MJPEG quality, overriding the config's camera.
    #[arg(long)]
    mjpeg_quality: Option<u8>,
    /// Which XL-80 log(s) to write.
    #[arg(long, value_enum, default_value_t = Xl80Out::Both)]
    xl80: Xl80Out,
    /// Time the axis rests at each step, ms.
    #[arg(long, default_value_t = 300.0)]
    dwell_ms: f64,
}

/// One move on the virtual clock: the axis' own trapezoidal profile, started at `start_s`.
struct Move {
    start_s: f64,
    profile: Profile,
}

impl Move {
    fn plan(start_s: f64, from_um: f64, to_um: f64, p: &AxisParams) -> Move {
        Move {
            start_s,
            profile: Profile::plan(from_um, to_um, p),
        }
    }
    fn end_s(&self) -> f64 {
        self.start_s + self.profile.duration_s()
    }
    fn at(&self, t_s: f64) -> f64 {
        self.profile.position_after(t_s - self.start_s)
    }
}

/// The scripted motion as a `TruePosition` on a virtual clock starting at `t0`.
struct Script {
    t0: Instant,
    start_um: f64,
    moves: Vec<Move>,
    axis_dir: [f64; 2],
    leadscrew: Leadscrew,
}

impl TruePosition for Script {
    fn true_position_um(&self, t: Instant) -> [f64; 2] {
        let s = t.saturating_duration_since(self.t0).as_secs_f64();
        let x = match self.moves.iter().rev().find(|m| m.start_s <= s) {
            Some(m) => m.at(s),
            None => self.start_um,
        };
        let x = self.leadscrew.true_um(x);
        [x * self.axis_dir[0], x * self.axis_dir[1]]
    }
}

fn main() -> Result<()> {
    let args = Args::parse();
    let mut cfg = match &args.config {
        Some(p) => {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            SimRigConfig::parse(&text, &p.display().to_string())?
        }
        None => SimRigConfig::default(),
    };
    if let Some(b) = &args.board {
        cfg.board_file = Some(b.clone());
    }
    if let Some(q) = args.mjpeg_quality {
        cfg.camera.mjpeg_quality = Some(q);
    }
    cfg.seed = args.seed;
    cfg.axis.seed = args.seed;
    cfg.xl80.seed = args.seed;
    if args.frames == 0 {
        bail!("--frames must be at least 1");
    }
    if !(args.step_um.is_finite() && args.start_um.is_finite()) {
        bail!("--step-um and --start-um must be finite numbers");
    }
    if !(args.dwell_ms.is_finite() && args.dwell_ms > cfg.camera.exposure_ms) {
        bail!(
            "--dwell-ms {} must exceed the exposure ({} ms)",
            args.dwell_ms,
            cfg.camera.exposure_ms
        );
    }
    let frames_dir = args.out.join("frames");
    if args.out.join("steps.csv").exists() {
        bail!("{} already holds a session (steps.csv)", args.out.display());
    }
    std::fs::create_dir_all(&frames_dir)
        .with_context(|| format!("creating {}", frames_dir.display()))?;

    let board = cfg.board()?;
    let renderer =
        FrameRenderer::new(board, cfg.camera.clone(), cfg.seed)?.with_origin(cfg.origin_um);

    // The motion: rest 0.5 s at the start, then for each step move and dwell.
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.axis.seed);
    let err = Normal::new(0.0, cfg.axis.position_error_rms_um.max(0.0))
        .context("axis position_error_rms_um")?;
    let dwell_s = args.dwell_ms / 1000.0;
    let exposure_s = cfg.camera.exposure_ms / 1000.0;
    let mut t = 0.5;
    let mut here = args.start_um;
    let mut moves = Vec::new();
    let mut exposures = Vec::new();
    let mut commanded = Vec::new();
    for i in 0..args.frames {
        let target = args.start_um + i as f64 * args.step_um;
        let reached = target + err.sample(&mut rng);
        let m = Move::plan(t, here, reached, &cfg.axis);
        t = m.end_s();
        moves.push(m);
        here = reached;
        exposures.push(t + 0.5 * (dwell_s - exposure_s));
        t += dwell_s;
        commanded.push(target);
    }
    let script = Script {
        t0: Instant::now(),
        start_um: args.start_um,
        moves,
        axis_dir: cfg.axis_dir,
        leadscrew: cfg.leadscrew,
    };

    let n = cfg.camera.motion_samples.max(1);
    for (i, &e) in exposures.iter().enumerate() {
        let los: Vec<[f64; 2]> = (0..n)
            .map(|k| {
                let s = e + exposure_s * (k as f64 + 0.5) / n as f64;
                script.true_position_um(script.t0 + Duration::from_secs_f64(s))
            })
            .collect();
        let img = renderer.render(i as u64, &los);
        let p = frames_dir.join(format!("{i:04}.png"));
        img.save(&p)
            .with_context(|| format!("writing {}", p.display()))?;
    }
    let steps = args.out.join("steps.csv");
    let mut w =
        std::fs::File::create(&steps).with_context(|| format!("writing {}", steps.display()))?;
    writeln!(w, "index,position_um")?;
    for (i, c) in commanded.iter().enumerate() {
        writeln!(w, "{i},{c}")?;
    }

    // The interferometer saw the whole run, rest to rest.
    let rate = cfg.xl80.sample_rate_hz;
    let count = ((t + 0.5) * rate).ceil() as usize;
    let readings = Xl80::new(cfg.xl80.clone())?.capture(&script, script.t0, count);
    let start_sys = SystemTime::now();
    let formats: &[LogFormat] = match args.xl80 {
        Xl80Out::Csv => &[LogFormat::Csv],
        Xl80Out::Rtx => &[LogFormat::Rtx],
        Xl80Out::Both => &[LogFormat::Csv, LogFormat::Rtx],
        Xl80Out::None => &[],
    };
    for &f in formats {
        let p = args.out.join(format!("xl80.{}", f.extension()));
        write_log(&p, f, &cfg.xl80, start_sys, &readings)?;
    }
    let sim_toml = args.out.join("sim.toml");
    std::fs::write(&sim_toml, toml::to_string_pretty(&cfg)?)
        .with_context(|| format!("writing {}", sim_toml.display()))?;
    println!(
        "{}: {} frames at {} µm steps from {} µm, {} XL-80 samples over {:.1} s",
        args.out.display(),
        args.frames,
        args.step_um,
        args.start_um,
        count,
        t + 0.5
    );
    Ok(())
}
