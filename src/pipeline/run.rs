//! (being written)
use super::*;
use image::RgbImage;

/// Push-based pipeline (being written).
pub struct Pipeline {
    _opts: ProcessOptions,
}

/// Process frames already in memory.
pub fn process_frames(
    _frames: &[RgbImage],
    _positions_um: &[f64],
    _opts: &ProcessOptions,
) -> Result<ProcessResult, PipelineError> {
    Err(PipelineError::Other("not yet implemented".into()))
}
