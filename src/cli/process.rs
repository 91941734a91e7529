//! `rigctl process DIR`: measure target offsets in a folder of frames, offline.
//! The folder contract and the output are documented in docs/folder-format.md.

use crate::folder;
use crate::pipeline::{Combine, Estimator, Pipeline, ProcessOptions, Registration};
use anyhow::Context;
use std::path::PathBuf;

#[derive(Clone, Copy, clap::ValueEnum)]
pub enum EstimatorArg {
    Paper,
    Fit,
}

#[derive(Clone, Copy, clap::ValueEnum)]
pub enum CombineArg {
    Interp,
    Splat,
    Mean,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum RegistrationArg {
    Image,
    Positions,
}

#[derive(clap::Args)]
pub struct ProcessArgs {
    /// Folder holding frames/*.png and steps.csv.
    pub dir: PathBuf,
    /// Size of one camera pixel on the board.
    #[arg(long, default_value_t = 774.0)]
    pub scale_um_per_px: f64,
    /// Upsampling factor of the reconstruction (1 = none).
    #[arg(long, default_value_t = 1)]
    pub k: u32,
    #[arg(long, value_enum, default_value = "fit")]
    pub estimator: EstimatorArg,
    /// How frames are combined [default: interp when k > 1, else mean].
    #[arg(long, value_enum)]
    pub combine: Option<CombineArg>,
    /// Where each frame's displacement comes from.
    #[arg(long, value_enum, default_value = "image")]
    pub registration: RegistrationArg,
    /// Image displacement per unit of axis travel, "x,y" (the scene moves against the camera).
    #[arg(long, value_parser = parse_dir, default_value = "-1,0")]
    pub axis_dir: [f64; 2],
    /// Use the first N frames only.
    #[arg(long)]
    pub frames: Option<usize>,
    /// Also reconstruct the whole frame (written with --out).
    #[arg(long)]
    pub whole_frame: bool,
    /// Board file naming the targets and giving their nominal offsets.
    #[arg(long)]
    pub board: Option<PathBuf>,
    /// Write result.json and the reconstructions (16-bit PNG) here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print the result as one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

fn parse_dir(s: &str) -> Result<[f64; 2], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|e| format!("`{p}`: {e}")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [x, y] => Ok([x, y]),
        _ => Err(format!("want two numbers \"x,y\", got `{s}`")),
    }
}

impl ProcessArgs {
    pub fn options(&self) -> ProcessOptions {
        ProcessOptions {
            scale_um_per_px: self.scale_um_per_px,
            k: self.k,
            estimator: match self.estimator {
                EstimatorArg::Paper => Estimator::Paper,
                EstimatorArg::Fit => Estimator::Fit,
            },
            combine: match self.combine {
                Some(CombineArg::Interp) => Combine::Interp,
                Some(CombineArg::Splat) => Combine::Splat,
                Some(CombineArg::Mean) => Combine::Mean,
                None if self.k > 1 => Combine::Interp,
                None => Combine::Mean,
            },
            registration: match self.registration {
                RegistrationArg::Image => Registration::Image,
                RegistrationArg::Positions => Registration::Positions,
            },
            axis_dir: self.axis_dir,
            whole_frame: self.whole_frame,
        }
    }
}

pub fn run(args: ProcessArgs) -> anyhow::Result<()> {
    if args.frames == Some(0) {
        anyhow::bail!("--frames must be at least 1");
    }
    let board = match &args.board {
        Some(p) => Some(crate::sim::Board::load(p)?),
        None => None,
    };
    let dir = folder::open(&args.dir, args.frames)?;
    let mut pipeline = Pipeline::new(args.options(), board)?;
    // PNG decoding is most of a frame's cost: a scoped thread decodes batches of frames in
    // parallel while this one pushes the previous ones, in order (a bad frame is reported
    // when its turn comes, so the first bad frame in order is the one named).
    let batch = rayon::current_num_threads().max(1) * 2;
    let items: Vec<_> = dir.frames.iter().zip(&dir.positions_um).collect();
    std::thread::scope(|scope| -> anyhow::Result<()> {
        let (tx, rx) = std::sync::mpsc::sync_channel(batch);
        let paths: Vec<&std::path::PathBuf> = items.iter().map(|(p, _)| *p).collect();
        scope.spawn(move || {
            use rayon::prelude::*;
            for chunk in paths.chunks(batch) {
                let decoded: Vec<_> = chunk.par_iter().map(|p| folder::load_frame(p)).collect();
                for frame in decoded {
                    // The receiver stops early on the first error: nothing left to do.
                    if tx.send(frame).is_err() {
                        return;
                    }
                }
            }
        });
        for ((path, &pos), frame) in items.iter().zip(rx) {
            let rep = pipeline
                .push(&frame?, pos)
                .with_context(|| path.display().to_string())?;
            tracing::debug!(?rep, "frame");
        }
        Ok(())
    })?;
    let done = pipeline
        .finish()
        .with_context(|| args.dir.display().to_string())?;
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
