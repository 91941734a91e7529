//! (being written: the push-based pipeline)
use super::*;
use image::RgbImage;
use rigd_sim::Board;

/// What one pushed frame gave.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameReport {
    pub index: usize,
    pub targets_found: usize,
    /// Displacement of this frame from the first, measured in the image.
    pub image_shift_px: [f64; 2],
    pub process_ms: f64,
}

/// An image the pipeline made (a reconstruction), 16-bit grey.
pub struct NamedImage {
    /// File stem, e.g. `target-A` or `whole-frame`.
    pub name: String,
    pub image: image::ImageBuffer<image::Luma<u16>, Vec<u16>>,
}

pub struct Finished {
    pub result: ProcessResult,
    pub images: Vec<NamedImage>,
}

/// Push-based pipeline: `new`, `push` each frame with its position, `finish`.
pub struct Pipeline {
    _opts: ProcessOptions,
    _board: Option<Board>,
}

impl Pipeline {
    pub fn new(opts: ProcessOptions, board: Option<Board>) -> Result<Pipeline, PipelineError> {
        Ok(Pipeline {
            _opts: opts,
            _board: board,
        })
    }

    pub fn push(
        &mut self,
        _frame: &RgbImage,
        _position_um: f64,
    ) -> Result<FrameReport, PipelineError> {
        Err(PipelineError::Other("not yet implemented".into()))
    }

    pub fn finish(self) -> Result<Finished, PipelineError> {
        Err(PipelineError::Other("not yet implemented".into()))
    }
}

/// Process frames already in memory.
pub fn process_frames(
    frames: &[RgbImage],
    positions_um: &[f64],
    opts: &ProcessOptions,
    board: Option<Board>,
) -> Result<Finished, PipelineError> {
    let mut p = Pipeline::new(opts.clone(), board)?;
    for (f, &x) in frames.iter().zip(positions_um) {
        p.push(f, x)?;
    }
    p.finish()
}
