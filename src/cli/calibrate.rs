//! `rigctl calibrate DIR`: fit a calibration (each target's local scale, the field model)
//! from a folder scan of known displacements (docs/calibration.md).

use crate::acquisition::JobRegistration;
use crate::board::Board;
use crate::calibration::{Calibration, FitOptions, Reference, Scan};
use crate::folder::{self, FrameFile};
use crate::offline::push::{process_folder, FrameIn};
use crate::pipeline::{Combine, Estimator, Pipeline, ProcessOptions, Registration};
use anyhow::Context;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct CalibrateArgs {
    /// A folder of frames/*.png and steps.csv: a scan of known displacements (e.g. 40
    /// steps of 500 µm).
    pub dir: PathBuf,
    /// The global scale the runs it will convert are processed with, µm per px.
    #[arg(long, value_name = "UM")]
    pub scale_um_per_px: f64,
    /// Where to write the calibration record (JSON).
    #[arg(long)]
    pub out: PathBuf,
    /// Board file: its layout fixes the field's shape and names the targets.
    #[arg(long)]
    pub board: Option<PathBuf>,
    /// The length reference: steps.csv's position_um (commanded) or interferometer_um.
    #[arg(long, value_enum, default_value = "commanded")]
    pub registration: JobRegistration,
    /// Image displacement per unit of axis travel, "x,y" (a starting guess).
    #[arg(long, value_parser = super::process::parse_dir, allow_hyphen_values = true,
          value_name = "X,Y", default_value = "-1,0")]
    pub axis_dir: [f64; 2],
    /// Relative standard uncertainty of the reference's scale [commanded 1e-4,
    /// interferometer 1e-6].
    #[arg(long, value_name = "REL")]
    pub reference_rel_u: Option<f64>,
    /// Print the calibration record on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: CalibrateArgs) -> anyhow::Result<()> {
    let reference = match args.registration {
        JobRegistration::Interferometer => Reference::Interferometer,
        JobRegistration::Commanded => Reference::Commanded,
        JobRegistration::Image => anyhow::bail!(
            "--registration image: a calibration needs known displacements (commanded or interferometer)"
        ),
    };
    let board = args.board.as_deref().map(Board::load).transpose()?;
    let options = ProcessOptions {
        scale_um_per_px: args.scale_um_per_px,
        k: 1,
        estimator: Estimator::Fit,
        combine: Combine::Mean,
        registration: Registration::Image,
        axis_dir: args.axis_dir,
        piezo_dir: None,
        whole_frame: false,
    }
    .validate()?;
    let dir = folder::open(&args.dir, None)?;
    let steps = args.dir.join("steps.csv");
    let positions = match reference {
        Reference::Interferometer => folder::read_interferometer(&steps, dir.frames.len())?,
        Reference::Commanded => dir.positions_um.clone(),
    };
    let frames: Vec<FrameIn> = dir
        .frames
        .iter()
        .zip(&positions)
        .map(|(p, &x)| FrameIn {
            file: FrameFile::Path(p.clone()),
            position_um: x,
            piezo_um: None,
        })
        .collect();
    let mut pipeline = Pipeline::new(options.clone(), board.clone());
    pipeline.keep_images(false);
    pipeline.record_tracks(true);
    let done = process_folder(pipeline, &frames, &args.dir)?;
    let (w, h) = (done.result.width, done.result.height);
    let scan = Scan {
        frame_size: (w, h),
        scale_um_per_px: args.scale_um_per_px,
        axis_dir: args.axis_dir,
        reference,
        positions_um: positions,
        piezo_um: dir.piezo_um.clone(),
        targets: done.tracks,
    };
    let opts = FitOptions {
        board,
        date: crate::daemon::timing::rfc3339(std::time::SystemTime::now()),
        rig: Some(format!(
            "{w}x{h} frames from {}, {} µm/px given",
            args.dir.display(),
            args.scale_um_per_px
        )),
        reference_rel_u: args.reference_rel_u,
    };
    let cal = Calibration::fit(&scan, &opts).with_context(|| args.dir.display().to_string())?;
    crate::calibration_file::save(&args.out, &cal)?;
    if args.json {
        println!("{}", serde_json::to_string(&cal)?);
    } else {
        print!("{}", summary(&cal));
        println!("written to {}", args.out.display());
    }
    Ok(())
}

/// A few lines: the field's residuals and per target its local scale and uncertainty.
pub fn summary(cal: &Calibration) -> String {
    let f = &cal.field;
    let mut s = format!(
        "calibration {} ({:?}, {} frames, step {} µm, {} layout): field model residual RMS {:.2} µm, max {:.2} µm\n",
        cal.id, cal.method, cal.scan.frames, cal.scan.step_um, f.layout, f.residual_rms_um, f.residual_max_um
    );
    for p in &f.parameters {
        s += &format!("  {:<15} {:>14.6e} ± {:.2e}\n", p.name, p.value, p.u);
    }
    s += "  target  centre_px           µm/px (own)   µm/px (model)  u_rel   line RMS µm\n";
    for t in &cal.targets {
        s += &format!(
            "  {:<7} ({:>7.1}, {:>6.1})  {:>9.3} ±{:.3} {:>9.3}  {:.1e}  {:.2}\n",
            t.name.as_deref().unwrap_or("-"),
            t.centre_px[0],
            t.centre_px[1],
            t.scale_um_per_px,
            t.scale_u_um_per_px,
            t.model_scale_um_per_px,
            t.model_scale_rel_u,
            t.residual_rms_um
        );
    }
    s
}
