//! Calibration from the stage: the local µm per px at each target and a field model for
//! the whole frame, fitted from a scan of known displacements, and the conversion of a
//! measured offset with it (docs/calibration.md).
//!
//! One global `scale_um_per_px` is wrong by a few per cent across a frame whose board is a
//! degree or two off parallel and whose lens has barrel distortion. A scan of known
//! displacements (the stage commanded, or read by the interferometer; e.g. 40 x 500 µm)
//! moves every target across the image by a known length: each target's centres give its
//! own displacement per µm (a straight line), and all of them together a field model
//! ([`FieldModel`]: board µm -> image px, a homography and radial distortion) fitted by
//! Levenberg–Marquardt, with the stage's direction on the board a parameter.
//!
//! Use:
//! ```ignore
//! let scan = Scan { frame_size, scale_um_per_px, axis_dir, reference, positions_um,
//!                   piezo_um: None, targets };   // targets: Pipeline::record_tracks
//! let cal = Calibration::fit(&scan, &FitOptions { board: Some(board), ..Default::default() })?;
//! cal.check(frame_size, scale_um_per_px, Some("paper"))?;          // warnings, or an error
//! let c = cal.convert(centre_px, offset_px, radii);  // c.offset_um, c.u_b_um, c.um_per_px
//! ```
//! The pipeline applies one itself: `Pipeline::set_calibration(Some(Arc::new(cal)))`.
//!
//! | module | job |
//! |---|---|
//! | `scan` | the input: positions, each target's centres per frame; errors |
//! | `model` | the field model: forward, inverse, local Jacobian, apparent circle centres |
//! | `lm` | Levenberg–Marquardt with the parameters' covariance |
//! | `fit` | each target's line, the field model's parameterisation and start |
//! | `outliers` | centres off their target's line, targets off the model: left out, recorded |
//! | `ink`, `ink_field`, `ink_margin` | the print's ink: its statistics, each target's map, how near the edges they read |
//! //! | `validation` | the field model against targets it was not fitted to; the model error every conversion carries |
//! | `record` | the [`Calibration`] record, its fit, its check and [`Calibration::convert`] |

mod fit;
pub mod ink;
pub mod ink_field;
pub mod ink_margin;
mod lm;
pub mod model;
mod outliers;
mod record;
pub mod scan;
#[cfg(test)]
mod tests;
pub mod validation;

pub use ink::{InkMap, InkStatistics};
pub use ink_field::InkField;
pub use ink_margin::{EdgeBand, InkMargin};
pub use model::FieldModel;
pub use outliers::Rejected;
pub use record::{
    Calibration, Converted, Estimate, FieldFit, Fingerprint, FitOptions, Radii, ScanSummary,
    TargetCalibration, CALIBRATION_VERSION, MIN_STEPS, MIN_TARGETS, MIN_TRAVEL_PX,
};
pub use scan::{CalibrationError, Reference, Scan, TargetTrack};
pub use validation::ModelCheck;

/// Relative standard uncertainty of the global scale when no calibration is applied: a
/// board up to ~2° off parallel and a webcam's barrel distortion change the local scale by
/// up to ±3.5 % across the frame (docs/sim.md, "Tilt"); a rectangular distribution of that
/// half-width has u = 3.5 % / √3 = 2 %.
pub const UNCALIBRATED_SCALE_REL_U: f64 = 0.02;
