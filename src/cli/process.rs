//! `rigctl process DIR`: measure target offsets offline, in a folder of frames (the folder
//! contract: docs/folder-format.md) or in a recorded session, each of whose runs is
//! processed as the daemon processed it (docs/reprocessing.md).

use crate::acquisition::JobRegistration;
use crate::board::Board;
use crate::calibration_file::Applied;
use crate::folder::{self, FrameFile};
use crate::offline::push::{decoders_for_one_run, process_folder, FrameIn};
use crate::offline::session_runs::process_session;
use crate::offline::Overrides;
use crate::pipeline::{
    Combine, Estimator, OptionError, Pipeline, ProcessOptions, ValidOptions, K_RANGE,
};
use anyhow::Context;
use std::path::{Path, PathBuf};

/// The processing flags `process` and `reprocess` share. On a session each one given
/// overrides the manifest's recorded value for every run; each one left out keeps it.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct ProcessingFlags {
    /// Size of one camera pixel on the board, µm [folder: 774; session: its rig's].
    #[arg(long, value_name = "UM")]
    pub scale_um_per_px: Option<f64>,
    #[arg(long, value_name = "K", value_parser = parse_k, help = k_help())]
    pub k: Option<u32>,
    /// How target centres are measured in each image [folder: fit; session: recorded].
    #[arg(long, value_enum)]
    pub estimator: Option<Estimator>,
    /// How frames are combined [folder: interp when k > 1, else mean; session: recorded].
    #[arg(long, value_enum)]
    pub combine: Option<Combine>,
    /// Where each frame's displacement comes from: the image, the commanded positions
    /// (`positions`: steps.csv's position_um) or the interferometer's readings
    /// (interferometer_um) [folder: image; session: recorded].
    #[arg(long, value_enum)]
    pub registration: Option<JobRegistration>,
    /// Image displacement per unit of axis travel, "x,y" (the scene moves against the
    /// camera) [folder: -1,0; session: its rig's].
    #[arg(long, value_parser = parse_dir, allow_hyphen_values = true, value_name = "X,Y")]
    pub axis_dir: Option<[f64; 2]>,
    /// The same per unit of piezo travel, for frames whose steps.csv has the piezo's
    /// positions (a 2-D plan's session) [folder: the axis's; session: its rig's].
    #[arg(long, value_parser = parse_dir, allow_hyphen_values = true, value_name = "X,Y")]
    pub piezo_dir: Option<[f64; 2]>,
    /// Also reconstruct the whole frame [session: recorded].
    #[arg(long)]
    pub whole_frame: bool,
    /// The camera's output curve: frames are measured in linear light [folder: linear;
    /// session: recorded].
    #[arg(long, value_enum)]
    pub response: Option<crate::pipeline::Response>,
    /// The print's ink density statistics, RMS,CORR_UM (e.g. 0.04,3000): the fit takes the
    /// print's uneven density as a prior (docs/method.md) [folder: none; session: its
    /// rig's].
    #[arg(long, value_parser = crate::pipeline::InkPrior::parse, value_name = "RMS,CORR_UM")]
    pub ink_prior: Option<crate::pipeline::InkPrior>,
    /// Do not take the print's ink statistics the calibration learnt from its scan as the
    /// fit's prior (without `--ink-prior`, the fit then takes the print as evenly inked).
    #[arg(long)]
    pub no_calibration_ink: bool,
    /// A calibration record (`rigctl calibrate --out`): offsets converted by its field
    /// model instead of the global scale, with its type-B uncertainty; a calibration of
    /// another frame size is refused (docs/calibration.md).
    #[arg(long, value_name = "FILE")]
    pub calibration: Option<PathBuf>,
    /// Convert at the global scale, even a session whose job applied a calibration (without
    /// it, `process SESSION` applies the calibration the daemon did).
    #[arg(long, conflicts_with = "calibration")]
    pub no_calibration: bool,
}

fn k_help() -> String {
    format!(
        "Upsampling factor of the reconstruction, {}..={} (the pipeline's K_RANGE, as the \
         daemon's) [folder: 1; session: each run's recorded k]",
        K_RANGE.start(),
        K_RANGE.end()
    )
}

impl ProcessingFlags {
    /// The calibration file, read and checked (its version), if one is given.
    pub fn calibration(&self) -> anyhow::Result<Option<Applied>> {
        self.calibration.as_deref().map(Applied::load).transpose()
    }

    pub fn overrides(&self) -> Overrides {
        Overrides {
            k: self.k,
            estimator: self.estimator,
            combine: self.combine,
            registration: self.registration,
            whole_frame: self.whole_frame.then_some(true),
            scale_um_per_px: self.scale_um_per_px,
            axis_dir: self.axis_dir,
            piezo_dir: self.piezo_dir,
            response: self.response,
            ink_prior: self.ink_prior,
            calibration_ink: self.no_calibration_ink.then_some(false),
        }
    }

    /// A plain folder's options: the flags, else the folder contract's defaults, checked
    /// against the pipeline's limits.
    pub fn folder_options(&self) -> Result<ValidOptions, OptionError> {
        let k = self.k.unwrap_or(1);
        ProcessOptions {
            scale_um_per_px: self.scale_um_per_px.unwrap_or(774.0),
            k,
            estimator: self.estimator.unwrap_or_default(),
            combine: self
                .combine
                .unwrap_or(crate::acquisition::job::combine_for(k)),
            registration: self.registration.unwrap_or_default().pipeline(),
            axis_dir: self.axis_dir.unwrap_or([-1.0, 0.0]),
            piezo_dir: self.piezo_dir,
            whole_frame: self.whole_frame,
            response: self.response.unwrap_or_default(),
            ink_prior: self.ink_prior,
            calibration_ink: !self.no_calibration_ink,
        }
        .validate()
    }
}

#[derive(clap::Args)]
#[command(
    after_help = "A session (DIR holds manifest.json) is processed run by run as the daemon \
                  processed it: its board, scale, directions, runs, cases and repeats, each \
                  run's recorded options and registration. Flags given override the recorded \
                  options (--k, --estimator, --combine, --registration, --whole-frame, \
                  --scale-um-per-px, --axis-dir, --piezo-dir, --board); the output is the \
                  daemon's result.json document (every run, and the study)."
)]
pub struct ProcessArgs {
    /// A session folder (manifest.json), or a folder holding frames/*.png and steps.csv.
    pub dir: PathBuf,
    #[command(flatten)]
    pub flags: ProcessingFlags,
    /// Use the first N frames only (of a session: its first N frames, over its runs).
    #[arg(long, value_name = "N")]
    pub frames: Option<usize>,
    /// Board file naming the targets and giving their nominal offsets [session: its rig's].
    #[arg(long)]
    pub board: Option<PathBuf>,
    /// Write result.json and the reconstructions (16-bit PNG) here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print the result as one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// `--k` in the pipeline's [`K_RANGE`], refused with the pipeline's own message.
pub(crate) fn parse_k(s: &str) -> Result<u32, String> {
    let k: u32 = s.parse().map_err(|e| format!("`{s}`: {e}"))?;
    if !K_RANGE.contains(&k) {
        return Err(OptionError::K { got: k }.to_string());
    }
    Ok(k)
}

/// A finite number: `NaN` and `inf` parse as f64 but mean nothing as a distance or time.
pub(crate) fn finite(s: &str) -> Result<f64, String> {
    let x: f64 = s.trim().parse().map_err(|e| format!("`{s}`: {e}"))?;
    match x.is_finite() {
        true => Ok(x),
        false => Err(format!("`{s}` is not a finite number")),
    }
}

pub(crate) fn parse_dir(s: &str) -> Result<[f64; 2], String> {
    let v: Vec<f64> = s.split(',').map(finite).collect::<Result<_, _>>()?;
    match v[..] {
        [x, y] => Ok([x, y]),
        _ => Err(format!("want two numbers \"x,y\", got `{s}`")),
    }
}

/// Whether `dir` is a recorded session (it has a manifest).
pub fn is_session(dir: &Path) -> bool {
    dir.join(crate::session::MANIFEST).exists()
}

pub fn run(args: ProcessArgs) -> anyhow::Result<()> {
    if args.frames == Some(0) {
        anyhow::bail!("--frames must be at least 1");
    }
    let board = match &args.board {
        Some(p) => Some(Board::load(p)?),
        None => None,
    };
    match is_session(&args.dir) {
        true => run_session(&args, board),
        false => run_folder(&args, board),
    }
}

/// A session: every run as the daemon processed it.
fn run_session(args: &ProcessArgs, board: Option<Board>) -> anyhow::Result<()> {
    let ov = args.flags.overrides();
    let s = crate::session::Session::open(&args.dir)?;
    let keep = args.out.is_some();
    let cal = match args.flags.calibration()? {
        Some(c) => Some(c),
        None if args.flags.no_calibration => None,
        None => {
            let cal = crate::offline::session_runs::recorded_calibration(&s)?;
            if let Some(c) = &cal {
                let id = &c.calibration.id;
                eprintln!("calibration {id} applied, as the daemon did ({})", c.source);
            }
            cal
        }
    };
    let decoders = decoders_for_one_run();
    let done = process_session(&s, &ov, board, cal.as_ref(), args.frames, keep, decoders)?;
    if let Some(out) = &args.out {
        std::fs::create_dir_all(out)
            .with_context(|| format!("{}: cannot create", out.display()))?;
        let settings = crate::offline::outputs::Settings {
            name: ov.settings_name(),
            overrides: ov,
            runs: done.runs.clone(),
            rigd: env!("CARGO_PKG_VERSION").into(),
            processed_unix_s: crate::timestamps::unix_s(std::time::SystemTime::now()),
        };
        let registration = crate::offline::outputs::registration_name(&settings.overrides, &s);
        let result = &done.result;
        crate::offline::outputs::write_outputs(
            out,
            result,
            &done.images,
            &settings,
            registration.as_deref(),
        )?;
    }
    if args.json {
        println!("{}", serde_json::to_string(&done.result)?);
        return Ok(());
    }
    for r in &done.result.runs {
        println!(
            "run {} ({}, repeat {}, {} frames at {} µm, k = {}):",
            r.run, r.case, r.repeat, r.frames, r.step_um, r.k
        );
        match (&r.result, &r.error) {
            (Some(res), _) => print!("{}", crate::report::result_text(res)),
            (None, e) => println!("  failed: {}", e.as_deref().unwrap_or("no result")),
        }
    }
    if let (Some(study), true) = (&done.result.study, done.result.runs.len() > 1) {
        print!("\n{}", crate::acquisition::study::tables(study));
    }
    Ok(())
}

/// A plain folder (docs/folder-format.md): one scan of all its frames.
fn run_folder(args: &ProcessArgs, board: Option<Board>) -> anyhow::Result<()> {
    // Every option is checked before a frame is read.
    let options = args.flags.folder_options()?;
    let cal = args.flags.calibration()?;
    let dir = folder::open(&args.dir, args.frames)?;
    let positions = match args.flags.registration {
        Some(JobRegistration::Interferometer) => {
            folder::read_interferometer(&args.dir.join("steps.csv"), dir.frames.len())?
        }
        _ => dir.positions_um.clone(),
    };
    let frames: Vec<FrameIn> = dir
        .frames
        .iter()
        .enumerate()
        .map(|(i, p)| FrameIn {
            file: FrameFile::Path(p.clone()),
            position_um: positions[i],
            piezo_um: dir.piezo_um.as_ref().map(|v| v[i]),
        })
        .collect();
    let mut pipeline = Pipeline::new(options, board);
    // The reconstructions are written only with --out: otherwise not converted at all.
    pipeline.keep_images(args.out.is_some());
    if let Some(c) = &cal {
        c.apply(&mut pipeline);
    }
    let done = process_folder(pipeline, &frames, &args.dir)?;
    if let Some(out) = &args.out {
        folder::write_outputs(out, &done.result, &done.images)?;
    }
    if args.json {
        println!("{}", serde_json::to_string(&done.result)?);
    } else {
        print!("{}", crate::report::result_text(&done.result));
    }
    Ok(())
}
