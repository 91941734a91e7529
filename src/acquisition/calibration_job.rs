//! The calibration job (`job.calibrate`, docs/calibration.md "In the daemon"): a line on the
//! axis in large known steps, captured and recorded only; the daemon then fits the
//! calibration from the session's frames (`offline::calibrate`, the code path of `rigctl
//! calibrate DIR`) and keeps the record in the data root (`crate::calibration_store`).

use crate::acquisition::job::{JobRegistration, JobSpec};
use crate::acquisition::plan::PlanError;
use crate::calibration::{Reference, MIN_STEPS};
use crate::pipeline::{Combine, Estimator};
use serde::{Deserialize, Serialize};

/// Default scan: 40 steps of 500 µm (20 mm; ~26 px of travel at 774 µm/px).
pub const DEFAULT_STEPS: u32 = 40;
pub const DEFAULT_STEP_UM: f64 = 500.0;

fn default_steps() -> u32 {
    DEFAULT_STEPS
}
fn default_step_um() -> f64 {
    DEFAULT_STEP_UM
}

/// The length reference of a calibration scan.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    Serialize,
    Deserialize,
    clap::ValueEnum,
    schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum ScanReference {
    /// The commanded positions.
    #[default]
    Commanded,
    /// The interferometer's reading at each frame (the job fails at a frame without one).
    Interferometer,
}

impl From<ScanReference> for Reference {
    fn from(r: ScanReference) -> Reference {
        match r {
            ScanReference::Commanded => Reference::Commanded,
            ScanReference::Interferometer => Reference::Interferometer,
        }
    }
}

impl From<ScanReference> for JobRegistration {
    fn from(r: ScanReference) -> JobRegistration {
        match r {
            ScanReference::Commanded => JobRegistration::Commanded,
            ScanReference::Interferometer => JobRegistration::Interferometer,
        }
    }
}

/// A calibration scan: `steps` frames `step_um` apart on the axis, from the job's
/// `start_um` (default: the rig's scan start).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct CalibrationScan {
    /// Frames of the scan (default 40, at least 5).
    #[serde(default = "default_steps")]
    pub steps: u32,
    /// Distance between frames, µm (default 500): every target should travel 20-30 px.
    #[serde(default = "default_step_um")]
    pub step_um: f64,
    /// The length reference: commanded positions (default) or the interferometer's.
    #[serde(default)]
    pub registration: ScanReference,
    /// Relative standard uncertainty of the reference's scale (default: commanded 1e-4,
    /// interferometer 1e-6).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference_rel_u: Option<f64>,
}

impl Default for CalibrationScan {
    fn default() -> Self {
        CalibrationScan {
            steps: DEFAULT_STEPS,
            step_um: DEFAULT_STEP_UM,
            registration: ScanReference::default(),
            reference_rel_u: None,
        }
    }
}

/// A calibration job as submitted: `calibrate` sets the scan and its processing, so the
/// fields it decides must be left out.
pub fn check_submitted(spec: &JobSpec) -> Result<(), PlanError> {
    let Some(c) = &spec.calibrate else {
        return Ok(());
    };
    let conflicts = [
        ("study", spec.study.is_some()),
        ("plan", spec.plan.is_some()),
        ("step_um", spec.step_um.is_some()),
        ("steps", spec.steps.is_some()),
        ("k", spec.k.is_some()),
        ("estimator", spec.estimator.is_some()),
        ("combine", spec.combine.is_some()),
        ("registration", spec.registration.is_some()),
        ("whole_frame", spec.whole_frame.is_some()),
        ("interval_s", spec.interval_s.is_some()),
        ("repeats", spec.repeats != 1),
        ("stage", spec.stage != crate::acquisition::StageKind::Axis),
    ];
    if let Some((name, _)) = conflicts.iter().find(|(_, set)| *set) {
        return Err(PlanError(format!(
            "`{name}`: a calibration job's scan and processing are set by `calibrate` \
             (steps, step_um, registration); leave `{name}` out"
        )));
    }
    if c.steps < MIN_STEPS as u32 {
        return Err(PlanError(format!(
            "`calibrate.steps` must be at least {MIN_STEPS}, got {}",
            c.steps
        )));
    }
    if !(c.step_um.is_finite() && c.step_um != 0.0) {
        return Err(PlanError(format!(
            "`calibrate.step_um` must be a finite non-zero length, got {}",
            c.step_um
        )));
    }
    match c.reference_rel_u {
        Some(u) if !(u.is_finite() && u >= 0.0) => Err(PlanError(format!(
            "`calibrate.reference_rel_u` must be a finite number >= 0, got {u}"
        ))),
        _ => Ok(()),
    }
}

/// `spec` with the scan and processing its `calibrate` decides: a line of `steps` x
/// `step_um` on the axis, recorded only (the fit measures the frames once the scan is on
/// disk), registered by the scan's reference so an interferometer scan has every reading.
pub fn resolve(spec: &mut JobSpec) {
    let Some(c) = spec.calibrate.clone() else {
        return;
    };
    spec.step_um = Some(c.step_um);
    spec.steps = Some(c.steps);
    spec.k = Some(1);
    spec.estimator = Some(Estimator::Fit);
    spec.combine = Some(Combine::Mean);
    spec.registration = Some(c.registration.into());
    spec.whole_frame = Some(false);
    spec.process = false;
}
