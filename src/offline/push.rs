//! Frames on disk pushed through one run's pipeline, in order, with PNG decoding ahead of
//! the pipeline on decoder threads: what `rigctl process` (a folder, or each run of a
//! session) and `rigctl reprocess` (each run of each session) share.

use super::ahead::Ahead;
use crate::folder::{FolderError, FrameFile, FrameReader, RowGate};
use crate::pipeline::measure::{FrameEstimates, Measurer};
use crate::pipeline::Pipeline;
use crate::pipeline::PipelineError;
use image::RgbImage;
use std::sync::atomic::AtomicU32;
use std::sync::{Arc, Mutex, OnceLock};

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
/// `decoders` threads decode ahead, each taking the next frame in order when it is free (at
/// most two per decoder beyond the one being pushed: [`Ahead`]), while this thread pushes
/// the frames in order (a bad frame is reported when its turn comes, so the first bad frame
/// in order is named). Pushed frames go back to a pool whose buffers the decoders reuse.
/// Once frame 0 has placed the targets, the decoders stop at the last row the pipeline will
/// read (plus room for the frames decoded ahead to move); a frame that moved further is
/// decoded again whole. From frame 0 on, a decoder also measures the targets of the frame
/// it decoded (the pipeline's [`Measurer`]): the fits run on every core in parallel,
/// rather than behind the pushing thread, which only accumulates.
pub fn push_frames(
    pipeline: &mut Pipeline,
    frames: &[FrameIn],
    decoders: usize,
) -> Result<(), PushError> {
    let workers = decoders.max(1);
    // Every frame must be the size frame 0's header says (within the frame limits): a
    // frame of another size is refused before its pixels are allocated.
    let size = match frames.first() {
        Some(f) => Some(f.file.size()?),
        None => None,
    };
    let pool = Mutex::new(Vec::<RgbImage>::new());
    let rows_wanted = Arc::new(AtomicU32::new(u32::MAX));
    pipeline.share_rows_needed(rows_wanted.clone(), ROWS_MARGIN);
    let measurer = Arc::new(OnceLock::new());
    pipeline.share_measurer(measurer.clone());
    // Closed while frame 0 is detected and fitted: sharing the cores with the decoders
    // made that serial step 3-4x longer (5-9 ms against ~2), every later frame behind it.
    let gate = RowGate::default();
    let window = FRAMES_AHEAD_PER_DECODER * workers;
    let ahead = Ahead::new(frames.len(), window);
    // Frame i goes through slot i % window, filled by whichever decoder took it: no frame is
    // taken before the one `window` earlier was pushed, so a slot is free when it is filled
    // (and a run of any length holds `window` slots).
    let (slots_in, slots_out): (Vec<_>, Vec<_>) = (0..window)
        .map(|_| std::sync::mpsc::sync_channel(1))
        .unzip();
    std::thread::scope(|scope| -> Result<(), PushError> {
        // However the pushing ends (done, a bad frame, a refusal), the decoders stop.
        let _stop = StopOnDrop(&ahead, &gate);
        for _ in 0..workers {
            let (pool, rows_wanted, ahead, slots) = (&pool, &*rows_wanted, &ahead, &slots_in);
            let (measurer, gate) = (&*measurer, &gate);
            scope.spawn(move || {
                let mut reader = FrameReader::expecting(size);
                while let Some(i) = ahead.take() {
                    let reuse = pool.lock().ok().and_then(|mut p| p.pop());
                    let read = reader
                        .read_file_rows_gated(&frames[i].file, reuse, rows_wanted, gate)
                        .map(|(frame, rows)| {
                            let pre = measure_ahead(measurer.get(), &frame, rows, (i, &frames[i]));
                            (frame, rows, pre)
                        });
                    // The pusher stops early on the first error: nothing left to do.
                    if slots[i % window].send(read).is_err() {
                        return;
                    }
                }
            });
        }
        let mut again = FrameReader::expecting(size);
        for (i, f) in frames.iter().enumerate() {
            let slot = &slots_out[i % window];
            let (frame, rows, pre) = slot.recv().map_err(|_| PushError::Decoder)??;
            if i == 0 {
                gate.close();
            }
            let pushed = push_one(pipeline, (i, f), (frame, rows, pre), &mut again);
            gate.open();
            let frame = pushed?;
            ahead.consumed(i);
            if let Ok(mut p) = pool.lock() {
                p.push(frame);
            }
        }
        Ok(())
    })
}

/// Frames a decoder may have decoded or be decoding beyond the one being pushed.
const FRAMES_AHEAD_PER_DECODER: usize = 2;

struct StopOnDrop<'a>(&'a Ahead, &'a RowGate);

impl Drop for StopOnDrop<'_> {
    fn drop(&mut self) {
        self.0.stop();
        self.1.open();
    }
}

/// Frame `i`'s targets measured on this (decoder's) thread, once frame 0 is in.
fn measure_ahead(
    m: Option<&Measurer>,
    frame: &RgbImage,
    rows: u32,
    (i, f): (usize, &FrameIn),
) -> Option<FrameEstimates> {
    let at = [f.position_um, f.piezo_um.unwrap_or(0.0)];
    m?.measure(frame, rows, i, at)
}

/// Push frame `i` (decoded down to `rows`, perhaps measured already), decoding it again
/// whole if the pipeline needs rows below; the buffer comes back for reuse.
fn push_one(
    pipeline: &mut Pipeline,
    (i, f): (usize, &FrameIn),
    (frame, rows, pre): (RgbImage, u32, Option<FrameEstimates>),
    again: &mut FrameReader,
) -> Result<RgbImage, PushError> {
    let refused = |source| PushError::Pipeline {
        nth: i,
        file: f.file.clone(),
        source,
    };
    let pushed = pipeline.push_measured(&frame, rows, (f.position_um, f.piezo_um), pre);
    Ok(match pushed.map_err(refused)? {
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
