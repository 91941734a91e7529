//! The averaging pipeline: frames + positions -> measured target offsets.
//!
//! detect targets -> register frames -> (reconstruct on a k-times finer grid) -> measure.
//! Push-based so the daemon can process frame i while the axis moves to i+1:
//! `let mut p = Pipeline::new(opts.validate()?, board); p.push(frame, position_um)?; ...`
//! then `p.finish()`. The options' limits are checked once, by [`ProcessOptions::validate`].
//! `process_frames` is the same for a folder of frames already on disk.
//!
//! Conventions: image coordinates in pixels with pixel centres at integers (OpenCV's);
//! x to the right, y down; lengths on the board in micrometres.

pub mod accumulate;
pub mod detect;
pub mod estimate;
pub mod focus;
pub mod lateral;
pub mod layout;
pub mod mean;
pub mod measure;
pub mod options;
pub mod plane;
pub mod reconstruct;
pub mod register;
pub mod response;
pub mod run;
pub mod stats;

pub use estimate::{
    bumps_at, ink_density, DensitySample, InkMean, InkShape, DENSITY_EDGE_MARGIN_S,
    DENSITY_READ_MARGIN_S,
};
pub use options::{InkPrior, OptionError, ProcessOptions, ValidOptions, K_RANGE, MAX_K};
pub use response::Response;
pub use run::{process_frames, Pipeline};

use serde::{Deserialize, Serialize};

// With feature `clap` the three option enums below are command-line values; each `value(name)`
// pins rigctl's spelling (the same as serde's), so renaming a variant cannot change the CLI.

/// How a circle centre is estimated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum Estimator {
    /// What the paper did: centroids of the thresholded red regions.
    #[cfg_attr(feature = "clap", value(name = "paper"))]
    Paper,
    /// Least-squares fit of a blurred ring-and-disk model to the pixels (default).
    #[cfg_attr(feature = "clap", value(name = "fit"))]
    #[default]
    Fit,
}

/// How frames are combined before (or instead of) measuring.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum Combine {
    /// The paper's: interpolate each frame by k (cubic), shift on the fine grid, average.
    #[cfg_attr(feature = "clap", value(name = "interp"))]
    Interp,
    /// Direct shift-and-add: each low-resolution pixel accumulated onto the fine grid.
    #[cfg_attr(feature = "clap", value(name = "splat"))]
    Splat,
    /// No reconstruction: measure every frame, average the per-frame estimates.
    #[cfg_attr(feature = "clap", value(name = "mean"))]
    #[default]
    Mean,
}

/// Where each frame's displacement comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
#[serde(rename_all = "snake_case")]
pub enum Registration {
    /// Measured in the image from the targets' outer circles (the paper's).
    #[cfg_attr(feature = "clap", value(name = "image"))]
    #[default]
    Image,
    /// From the recorded positions (commanded or interferometer) and the scale.
    #[cfg_attr(feature = "clap", value(name = "positions"))]
    Positions,
}

/// One measured target.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct ObjectResult {
    /// Board name of the target when a board was given and the target matched.
    pub name: Option<String>,
    /// Outer circle centre in the first frame.
    pub centre_px: [f64; 2],
    /// Inner centre minus outer centre, camera pixels.
    pub offset_px: [f64; 2],
    /// The same in micrometres on the board: `offset_px` x `scale_um_per_px`, or, when a
    /// calibration was applied (`ProcessResult::calibration`), converted by its field model.
    pub offset_um: [f64; 2],
    /// One-sigma uncertainty of `offset_um` (from the fit, or the frame-to-frame scatter), in
    /// the same scale: through the calibration when one converted the offset.
    pub sigma_um: Option<[f64; 2]>,
    /// Nominal offset from the board file.
    pub nominal_um: Option<[f64; 2]>,
    pub outer_radius_px: f64,
    pub inner_radius_px: f64,
    /// Frames that contributed.
    pub frames: usize,
    /// Size on the board of one pixel of the grid the offset was measured on
    /// (`scale_um_per_px / k` for a reconstruction, the camera pixel otherwise).
    pub effective_pixel_um: f64,
    /// Combined standard uncertainty of `offset_um` (GUM): `sqrt(u_a² + u_b²)` per axis.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub u_um: Option<[f64; 2]>,
    /// Type A: from the frames' scatter (the per-frame offsets' standard error, never below
    /// the fit's covariance; the fit's covariance for one frame).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub u_a_um: Option<[f64; 2]>,
    /// Type B: the calibration's (field model, reference scale), else the global scale's
    /// assumed `calibration::UNCALIBRATED_SCALE_REL_U` of the offset's length; and
    /// `u_ink_um` when there is one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub u_b_um: Option<[f64; 2]>,
    /// Type B of the ink model, part of `u_b_um`: on a target whose print the fit found
    /// uneven (it freed the contrast planes), the correction the planes made to the offset
    /// as the half-width of a rectangular distribution (|planes − even-ink| / √3).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub u_ink_um: Option<[f64; 2]>,
    /// `offset_px` x `scale_um_per_px`, when a calibration gave `offset_um` instead.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset_global_um: Option<[f64; 2]>,
}

/// The calibration a result was converted with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct CalibrationUsed {
    pub id: String,
    pub date: String,
    pub method: crate::calibration::Reference,
    /// Where it was read from, when the caller says.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    /// Mismatches that did not stop it (another scale or board than it was fitted with).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    /// The print's ink statistics it learnt, when the run took them as the fit's prior.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ink_prior: Option<InkPrior>,
    /// How many targets' priors were centred on its map of their ink.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub ink_maps: usize,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// A target candidate that was found but not measured, and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct Skipped {
    pub centre_px: [f64; 2],
    pub reason: String,
}

/// Per step: the displacement measured in the image against the one the positions predict.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct StepResidual {
    pub index: usize,
    pub position_um: f64,
    /// The piezo's position, in a run that moves it besides its stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub piezo_um: Option<f64>,
    pub image_shift_px: [f64; 2],
    pub position_shift_px: [f64; 2],
    /// image minus position, micrometres on the board.
    pub residual_um: [f64; 2],
}

/// Every step's residual in brief (`ProcessResult::steps` lists only the first
/// [`register::MAX_LISTED_STEPS`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct StepSummary {
    /// Steps the run had.
    pub frames: usize,
    /// Root mean square of `residual_um` over every step, per axis.
    pub rms_residual_um: [f64; 2],
    /// The step with the largest residual (by its length), wherever it is in the run.
    pub largest: Option<StepResidual>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schemars", derive(schemars::JsonSchema))]
pub struct ProcessResult {
    pub options: ProcessOptions,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub objects: Vec<ObjectResult>,
    pub skipped: Vec<Skipped>,
    /// Per step, the first [`register::MAX_LISTED_STEPS`] of the run.
    pub steps: Vec<StepResidual>,
    /// Every step, in brief (absent from results written before rigd 0.2: all steps listed).
    #[serde(default)]
    pub step_summary: StepSummary,
    /// The calibration the offsets were converted with (none: the global scale).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<CalibrationUsed>,
}

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("frame {index}: size {got:?} differs from the first frame's {want:?}")]
    FrameSize {
        index: usize,
        got: (u32, u32),
        want: (u32, u32),
    },
    #[error("no target found in frame {index}")]
    NoTarget { index: usize },
    #[error("no frames")]
    NoFrames,
    #[error(transparent)]
    Option(#[from] OptionError),
    #[error(transparent)]
    Calibration(#[from] crate::calibration::CalibrationError),
    #[error("{0}")]
    Other(String),
}
