//! Frames on disk pushed through one run's pipeline, in order, with PNG decoding ahead of
//! the pipeline on decoder threads: what `rigctl process` (a folder, or each run of a
//! session) and `rigctl reprocess` (each run of each session) share.

use crate::folder::{FolderError, FrameFile, FrameReader};
use crate::pipeline::Pipeline;
use crate::pipeline::PipelineError;
use image::RgbImage;
use std::sync::atomic::AtomicU32;
use std::sync::{Arc, Mutex};

/// Rows decoded below the last one the pipeline reads: room for the frames decoded ahead
/// (up to ~2 per decoder) to move down before a frame has to be decoded again.
const ROWS_MARGIN: u32 = 24;

/// One frame to push: its file, the position it registers by (the job's stage) and the
/// piezo's, when the run moves the piezo besides.
#[derive(Debug, Clone)]
pub struct FrameIn {
    pub file: FrameFile,
    pub position_um: f64,
    pub piezo_um: Option<f64>,
}

/// Why a run's frames could not all be pushed: a file that cannot be read as a frame (the
/// input is broken), or the pipeline refusing frame `nth` of the run (the run has no
/// result: the daemon records such a run's error and goes on).
#[derive(Debug, thiserror::Error)]
pub enum PushError {
    #[error(transparent)]
    Read(#[from] FolderError),
    #[error("{}: {source}", file.path().display())]
    Pipeline {
        nth: usize,
        file: FrameFile,
        source: PipelineError,
    },
    #[error("a frame decoder stopped")]
    Decoder,
}

/// Push `frames` into `pipeline` in order. PNG decoding is most of a frame's cost:
/// `decoders` threads take every W-th frame each and decode ahead while this thread pushes
/// the frames in order (a bad frame is reported when its turn comes, so the first bad frame
/// in order is named). Pushed frames go back to a pool whose buffers the decoders reuse.
/// Once frame 0 has placed the targets, the decoders stop at the last row the pipeline will
/// read (plus room for the frames decoded ahead to move); a frame that moved further is
/// decoded again whole.
pub fn push_frames(
    pipeline: &mut Pipeline,
    frames: &[FrameIn],
    decoders: usize,
) -> Result<(), PushError> {
    let workers = decoders.max(1);
    let pool = Mutex::new(Vec::<RgbImage>::new());
    let rows_wanted = Arc::new(AtomicU32::new(u32::MAX));
    pipeline.share_rows_needed(rows_wanted.clone(), ROWS_MARGIN);
    std::thread::scope(|scope| -> Result<(), PushError> {
        let mut queues = Vec::with_capacity(workers);
        for w in 0..workers {
            let (tx, rx) = std::sync::mpsc::sync_channel(1);
            queues.push(rx);
            let (pool, rows_wanted) = (&pool, &*rows_wanted);
            scope.spawn(move || {
                let mut reader = FrameReader::default();
                for f in frames.iter().skip(w).step_by(workers) {
                    let reuse = pool.lock().ok().and_then(|mut p| p.pop());
                    // The receiver stops early on the first error: nothing left to do.
                    if tx
                        .send(reader.read_file_rows_until(&f.file, reuse, rows_wanted))
                        .is_err()
                    {
                        return;
                    }
                }
            });
        }
        let mut again = FrameReader::default();
        for (i, f) in frames.iter().enumerate() {
            let (frame, rows) = queues[i % workers]
                .recv()
                .map_err(|_| PushError::Decoder)??;
            let refused = |source| PushError::Pipeline {
                nth: i,
                file: f.file.clone(),
                source,
            };
            let pushed = pipeline.push_rows_at(&frame, rows, f.position_um, f.piezo_um);
            let frame = match pushed.map_err(refused)? {
                Some(rep) => {
                    tracing::debug!(?rep, "frame");
                    frame
                }
                None => {
                    let (whole, _) = again.read_file_rows(&f.file, Some(frame), u32::MAX)?;
                    let rep = pipeline
                        .push_at(&whole, f.position_um, f.piezo_um)
                        .map_err(refused)?;
                    tracing::debug!(?rep, "frame");
                    whole
                }
            };
            if let Ok(mut p) = pool.lock() {
                p.push(frame);
            }
        }
        Ok(())
    })
}

/// A plain folder's frames through `pipeline` as one run, then its result; errors name
/// `dir` (`rigctl process DIR` and `rigctl calibrate DIR`).
pub fn process_folder(
    mut pipeline: Pipeline,
    frames: &[FrameIn],
    dir: &std::path::Path,
) -> anyhow::Result<crate::pipeline::run::Finished> {
    push_frames(&mut pipeline, frames, decoders_for_one_run()).map_err(|e| match e {
        PushError::Read(e) => anyhow::Error::new(e),
        other => anyhow::anyhow!("{other}"),
    })?;
    anyhow::Context::with_context(pipeline.finish(), || dir.display().to_string())
}

/// Decoder threads for one run processed alone: one per core, at most 4.
pub fn decoders_for_one_run() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get().min(4))
}
