//! `rigctl process DIR`: measure target offsets in a folder of frames, offline.
//! The folder contract and the output are documented in docs/folder-format.md.

use crate::folder;
use crate::pipeline::{
    Combine, Estimator, OptionError, Pipeline, ProcessOptions, Registration, ValidOptions, K_RANGE,
};
use anyhow::Context;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct ProcessArgs {
    /// Folder holding frames/*.png and steps.csv.
    pub dir: PathBuf,
    /// Size of one camera pixel on the board.
    #[arg(long, default_value_t = 774.0)]
    pub scale_um_per_px: f64,
    /// Upsampling factor of the reconstruction (1 = none; at most 32).
    #[arg(long, default_value_t = 1, value_parser = parse_k)]
    pub k: u32,
    /// How target centres are measured in each image.
    #[arg(long, value_enum, default_value = "fit")]
    pub estimator: Estimator,
    /// How frames are combined [default: interp when k > 1, else mean].
    #[arg(long, value_enum)]
    pub combine: Option<Combine>,
    /// Where each frame's displacement comes from.
    #[arg(long, value_enum, default_value = "image")]
    pub registration: Registration,
    /// Image displacement per unit of axis travel, "x,y" (the scene moves against the camera).
    #[arg(long, value_parser = parse_dir, default_value = "-1,0", allow_hyphen_values = true)]
    pub axis_dir: [f64; 2],
    /// The same per unit of piezo travel, for a folder whose steps.csv has the piezo's
    /// positions (a 2-D plan's session) [default: the axis's].
    #[arg(long, value_parser = parse_dir)]
    pub piezo_dir: Option<[f64; 2]>,
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

/// `--k` in the pipeline's [`K_RANGE`], refused with the pipeline's own message.
pub(crate) fn parse_k(s: &str) -> Result<u32, String> {
    let k: u32 = s.parse().map_err(|e| format!("`{s}`: {e}"))?;
    if !K_RANGE.contains(&k) {
        return Err(OptionError::K { got: k }.to_string());
    }
    Ok(k)
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
    /// The pipeline's options from the flags, checked against its limits.
    pub fn options(&self) -> Result<ValidOptions, OptionError> {
        ProcessOptions {
            scale_um_per_px: self.scale_um_per_px,
            k: self.k,
            estimator: self.estimator,
            combine: self.combine.unwrap_or(if self.k > 1 {
                Combine::Interp
            } else {
                Combine::Mean
            }),
            registration: self.registration,
            axis_dir: self.axis_dir,
            piezo_dir: self.piezo_dir,
            whole_frame: self.whole_frame,
        }
        .validate()
    }
}

/// Rows decoded below the last one the pipeline reads: room for the frames decoded ahead
/// (up to ~2 per decoder) to move down before a frame has to be decoded again.
const ROWS_MARGIN: u32 = 24;

pub fn run(args: ProcessArgs) -> anyhow::Result<()> {
    if args.frames == Some(0) {
        anyhow::bail!("--frames must be at least 1");
    }
    // Every option is checked before a frame is read.
    let options = args.options()?;
    let board = match &args.board {
        Some(p) => Some(crate::board::Board::load(p)?),
        None => None,
    };
    let dir = folder::open(&args.dir, args.frames)?;
    let mut pipeline = Pipeline::new(options, board);
    // The reconstructions are written only with --out: otherwise not converted at all.
    pipeline.keep_images(args.out.is_some());
    // PNG decoding is most of a frame's cost: decoder threads (one per core) take every
    // W-th frame each and decode ahead while this thread pushes the frames in order (a bad
    // frame is reported when its turn comes, so the first bad frame in order is named).
    // Pushed frames go back to a pool whose buffers the decoders reuse. Once frame 0 has
    // placed the targets, the decoders stop at the last row the pipeline will read (plus
    // room for the frames decoded ahead to move); a frame that moved further is decoded
    // again whole.
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get().min(4));
    let pool = std::sync::Mutex::new(Vec::<image::RgbImage>::new());
    let rows_wanted = std::sync::atomic::AtomicU32::new(u32::MAX);
    std::thread::scope(|scope| -> anyhow::Result<()> {
        let mut queues = Vec::with_capacity(workers);
        for w in 0..workers {
            let (tx, rx) = std::sync::mpsc::sync_channel(1);
            queues.push(rx);
            let (frames, pool, rows_wanted) = (&dir.frames, &pool, &rows_wanted);
            scope.spawn(move || {
                let mut reader = folder::FrameReader::default();
                for path in frames.iter().skip(w).step_by(workers) {
                    let reuse = pool.lock().ok().and_then(|mut p| p.pop());
                    let rows = rows_wanted.load(std::sync::atomic::Ordering::Relaxed);
                    // The receiver stops early on the first error: nothing left to do.
                    if tx.send(reader.read_rows(path, reuse, rows)).is_err() {
                        return;
                    }
                }
            });
        }
        let mut again = folder::FrameReader::default();
        for (i, (path, &pos)) in dir.frames.iter().zip(&dir.positions_um).enumerate() {
            let piezo = dir.piezo_um.as_ref().map(|p| p[i]);
            let (frame, rows) = queues[i % workers]
                .recv()
                .context("a frame decoder stopped")??;
            let ctx = || path.display().to_string();
            let pushed = pipeline.push_rows_at(&frame, rows, pos, piezo);
            let (frame, rep) = match pushed.with_context(ctx)? {
                Some(rep) => (frame, rep),
                None => {
                    let whole = again.read(path, Some(frame))?;
                    let rep = pipeline.push_at(&whole, pos, piezo).with_context(ctx)?;
                    (whole, rep)
                }
            };
            tracing::debug!(?rep, "frame");
            if let Some(rows) = pipeline.rows_needed(ROWS_MARGIN) {
                rows_wanted.store(rows, std::sync::atomic::Ordering::Relaxed);
            }
            if let Ok(mut p) = pool.lock() {
                p.push(frame);
            }
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
