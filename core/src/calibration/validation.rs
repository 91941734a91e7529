//! The field model checked against what it was not fitted to, and the model error every
//! conversion carries (docs/calibration.md, "Model error").
//!
//! The field model is a homography with radial distortion and the stage moving in the
//! board's plane. A real rig breaks it in ways its covariance cannot show: the rail a
//! degree out of the board's plane zooms the image over the scan, a lens has more than two
//! distortion terms. The covariance assumes the residuals are noise, so a model that misfits
//! by 58 µm still reports parameters to 1e-4. Two checks measure what the model cannot know:
//!
//! - **Leave one out** (5 targets or more): each target's own rate (its straight line
//!   through the scan, px per µm) against the rate the model fitted *without it* predicts
//!   where it sits. The mismatch beyond the line fits' own noise is the model's error in the
//!   local scale and direction, relative.
//! - **Residuals**: the model's residuals at each target beyond its own line's. A rate
//!   error `ε` leaves a residual ramp of RMS `ε·T/√12` over a travel of `T` px, so the
//!   excess reads as `ε`. The rates see only the scale along the stage; the residuals also
//!   see the targets' places across it (a lens the model's two distortion terms cannot
//!   describe), so both run and the larger u is kept.
//!
//! The excess (never less than what the check can resolve) becomes a relative standard
//! uncertainty ([`ModelCheck::model_rel_u`]) applied
//! to the offset's length on both axes: a 1-D scan measures the local scale along the stage
//! only, and the other direction is taken to be no better known.
//!
//! With no board (free layout) a 1-D scan leaves a gauge open: a rail out of the board's
//! plane zooms the image over the scan with the same radial flow a perspective along the
//! stage makes, so the fit cannot tell the zoom from a tilt, and picks the tilt. With a
//! board the print fixes the perspective and the zoom is fitted (`rail_zoom_per_um`);
//! without one [`gauge_rel_u`] allows for a rail up to 2° out of plane.

use super::fit::LineFit;
use super::model::FieldModel;
use nalgebra::Vector2;
use serde::{Deserialize, Serialize};

/// Fewest targets a leave-one-out check needs: one out, `MIN_TARGETS` left.
pub const MIN_LEAVE_ONE_OUT: usize = super::MIN_TARGETS + 1;

/// The field model against the scan's targets.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelCheck {
    /// `leave-one-out` or `residuals` (too few targets to leave one out).
    pub method: String,
    /// Targets checked.
    pub targets: usize,
    /// RMS relative mismatch of the targets against the model: with `leave-one-out` first,
    /// its rates along and across the stage's axis; from `residuals` alone, the ramp (a
    /// rate error) and the misplacement (a scale error over the nearest target's distance).
    pub rms_rel: [f64; 2],
    /// The RMS the line fits' own noise gives (their relative standard uncertainties).
    pub noise_rel: [f64; 2],
    /// The mismatch beyond the noise, or the check's resolution when it is smaller: the
    /// model's relative standard uncertainty, carried into every conversion's type B.
    pub model_rel_u: f64,
    /// Whether the mismatch is what the noise gives (a chi-square test at 99 %): when not,
    /// the model does not describe this rig, and `model_rel_u` says by how much.
    pub holds: bool,
    /// The checks that failed (`leave-one-out`, `residuals`): the rates failing says the
    /// field is not the model's; the residuals alone may also be a print off its design.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub failed: Vec<String>,
}

impl ModelCheck {
    /// The leave-one-out check and the residuals' together: each sees what the other may
    /// not (the rates along the stage; the places across it), so the larger u is kept.
    pub fn and(self, residuals: ModelCheck) -> ModelCheck {
        ModelCheck {
            method: format!("{} and {}", self.method, residuals.method),
            model_rel_u: self.model_rel_u.max(residuals.model_rel_u),
            holds: self.holds && residuals.holds,
            failed: [self.failed, residuals.failed].concat(),
            ..self
        }
    }
}

/// One target's rate against a prediction whose own relative variances (along, across) are
/// `predicted_var`: (mismatch, noise), relative, along and across the predicted direction.
pub(crate) fn rate_mismatch(
    line: &LineFit,
    predicted: Vector2<f64>,
    predicted_var: [f64; 2],
) -> ([f64; 2], [f64; 2]) {
    let speed = predicted.norm();
    let (along, across) = axes(predicted);
    let e = line.v - predicted;
    let var = |d: Vector2<f64>| (d.transpose() * line.v_cov * d)[0].max(0.0) / (speed * speed);
    (
        [e.dot(&along) / speed, e.dot(&across) / speed],
        [
            (var(along) + predicted_var[0]).sqrt(),
            (var(across) + predicted_var[1]).sqrt(),
        ],
    )
}

/// Unit vectors along and across a rate.
pub(crate) fn axes(v: Vector2<f64>) -> (Vector2<f64>, Vector2<f64>) {
    let along = v / v.norm();
    (along, Vector2::new(-along[1], along[0]))
}

/// A target's (mismatch, noise), relative, two components.
pub(crate) type Mismatch = ([f64; 2], [f64; 2]);

/// The check from per-target (mismatch, noise) pairs.
pub(crate) fn summarise(method: &str, per_target: &[Mismatch]) -> ModelCheck {
    let n = per_target.len().max(1) as f64;
    let ms = |f: &dyn Fn(&Mismatch) -> f64| per_target.iter().map(f).sum::<f64>() / n;
    let mis = [ms(&|t| t.0[0].powi(2)), ms(&|t| t.0[1].powi(2))];
    let noise = [ms(&|t| t.1[0].powi(2)), ms(&|t| t.1[1].powi(2))];
    let excess = (mis[0] - noise[0]).max(0.0) + (mis[1] - noise[1]).max(0.0);
    let dof = 2.0 * n;
    // The check cannot see an error below its own resolution (the mean square's standard
    // error over `dof` components): a model that passes is known only to that.
    let resolution = (noise[0] + noise[1]) * (2.0 / dof).sqrt();
    // Σ (e/σ)² over 2n components is χ² with 2n degrees of freedom when the model holds.
    let chi2: f64 = per_target
        .iter()
        .flat_map(|(e, s)| (0..2).map(move |k| (e[k] / s[k].max(1e-300)).powi(2)))
        .sum();
    let holds = chi2 <= dof + 2.33 * (2.0 * dof).sqrt();
    // A model that fails is wrong by different amounts at different places: the worst
    // target's excess, not the typical one, is what a conversion may meet.
    let worst = (per_target.iter())
        .map(|(e, s)| {
            (0..2)
                .map(|k| (e[k] * e[k] - s[k] * s[k]).max(0.0))
                .sum::<f64>()
        })
        .fold(0.0, f64::max);
    let excess = if holds { excess } else { excess.max(worst) };
    ModelCheck {
        method: method.into(),
        targets: per_target.len(),
        rms_rel: mis.map(f64::sqrt),
        noise_rel: noise.map(f64::sqrt),
        model_rel_u: excess.max(resolution).sqrt(),
        holds,
        failed: if holds { vec![] } else { vec![method.into()] },
    }
}

/// A target's (mismatch, noise) read from its residuals: the model's RMS residual beyond
/// its own line's, as a rate error over the travel (`ε = excess·√12 / travel`). Both in
/// px; the noise is the line's residual spread through the same relation over √steps.
pub(crate) fn residual_mismatch(
    model_rms_px: f64,
    line_rms_px: f64,
    travel_px: f64,
    steps: usize,
) -> ([f64; 2], [f64; 2]) {
    let excess = (model_rms_px.powi(2) - line_rms_px.powi(2)).max(0.0).sqrt();
    let k = 12f64.sqrt() / travel_px.max(1e-9);
    // The excess is over both axes: half of its square on each.
    let e = excess * k / 2f64.sqrt();
    let s = line_rms_px * k / (steps.max(1) as f64).sqrt() / 2f64.sqrt();
    ([e, e], [s, s])
}

/// The rail's largest angle to the board assumed where a scan cannot measure it, degrees
/// (as for the uncalibrated scale: a board set up by eye is within ~2° of the rail).
pub const RAIL_ANGLE_MAX_DEG: f64 = 2.0;

/// The free layout's gauge allowance at `centre_px`, relative: a rail up to
/// [`RAIL_ANGLE_MAX_DEG`] out of the board's plane zooms the image by `sin θ / Z` per µm,
/// the same radial flow as a perspective of that size along the stage, so the fit may put
/// a perspective there that is not. It changes the local scale by `κ·(b·d)` at a target
/// `b` along the stage direction `d`: a rectangular distribution of that half-width. The
/// distance `Z` is the focal length times the scale, the focal length taken as the frame's
/// half diagonal (a 90° diagonal field; a webcam's 60–90° make it longer, `κ` smaller).
pub fn gauge_rel_u(model: &FieldModel, stage_dir_rad: f64, centre_px: [f64; 2]) -> f64 {
    let Some(b) = model.inverse(centre_px) else {
        return 0.0;
    };
    let a = model.a_px_per_um;
    let px_per_um = (a[0][0] * a[1][1] - a[0][1] * a[1][0]).abs().sqrt();
    let z_um = model.norm_radius_px / px_per_um;
    let kappa = RAIL_ANGLE_MAX_DEG.to_radians().sin() / z_um;
    let along = b[0] * stage_dir_rad.cos() + b[1] * stage_dir_rad.sin();
    kappa * along.abs() / 3f64.sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix2;

    fn line(v: [f64; 2], sd: f64) -> LineFit {
        LineFit {
            x0_px: [0.0; 2],
            v: Vector2::new(v[0], v[1]),
            v_cov: Matrix2::identity() * sd * sd,
            w: Vector2::zeros(),
            residuals_px: Vec::new(),
        }
    }

    #[test]
    fn a_mismatch_splits_along_and_across_the_predicted_rate() {
        let l = line([1.01e-3, 0.02e-3], 1e-6);
        let (e, s) = rate_mismatch(&l, Vector2::new(1e-3, 0.0), [0.0, 3e-6]);
        assert!(
            (e[0] - 0.01).abs() < 1e-12 && (e[1] - 0.02).abs() < 1e-12,
            "{e:?}"
        );
        // The line's 1e-3 relative, and the prediction's own variance added.
        assert!(
            (s[0] - 1e-3).abs() < 1e-12 && (s[1] - 2e-3).abs() < 1e-12,
            "{s:?}"
        );
    }

    #[test]
    fn noise_alone_holds_and_an_excess_becomes_the_models_u() {
        // Mismatches the size of the noise: holds, and u is the check's resolution.
        let noisy: Vec<_> = (0..12)
            .map(|k| {
                let e = if k % 2 == 0 { 1e-4 } else { -1e-4 };
                ([e, -e], [1e-4, 1e-4])
            })
            .collect();
        let c = summarise("leave-one-out", &noisy);
        assert!(c.holds, "{c:?}");
        let resolution = (2e-8f64 * (2.0f64 / 24.0).sqrt()).sqrt();
        assert!((c.model_rel_u - resolution).abs() < 1e-12, "{c:?}");
        // Ten times the noise along the axis: does not hold, u is the excess.
        let off: Vec<_> = (0..12).map(|_| ([1e-3, 1e-4], [1e-4, 1e-4])).collect();
        let c = summarise("leave-one-out", &off);
        assert!(!c.holds, "{c:?}");
        assert!(
            (c.model_rel_u - (1e-6f64 - 1e-8).sqrt()).abs() < 1e-9,
            "{c:?}"
        );
    }

    #[test]
    fn a_residual_ramp_reads_as_the_rate_error_that_made_it() {
        // ε = 1e-3 over 30 px leaves a ramp of RMS 30e-3/√12 px.
        let ramp = 1e-3 * 30.0 / 12f64.sqrt();
        let (e, s) = residual_mismatch(ramp, 0.0, 30.0, 30);
        assert!((e[0].hypot(e[1]) - 1e-3).abs() < 1e-12, "{e:?}");
        assert_eq!(s, [0.0, 0.0]);
    }

    #[test]
    fn the_gauge_allowance_grows_along_the_stage_from_nothing_at_the_centre() {
        let m = FieldModel::plain((1280, 720), 774.0);
        let c = m.centre_px;
        assert!(gauge_rel_u(&m, 0.0, c) < 1e-12);
        // 500 px along the stage: sin 2° x 500 / 734.3 half diagonal, over √3.
        let want = 2f64.to_radians().sin() * 500.0 / m.norm_radius_px / 3f64.sqrt();
        let along = gauge_rel_u(&m, 0.0, [c[0] + 500.0, c[1]]);
        assert!((along - want).abs() < 1e-9, "{along} vs {want}");
        // Across the stage the zoom's flow is not the perspective's: none.
        assert!(gauge_rel_u(&m, 0.0, [c[0], c[1] + 300.0]) < 1e-12);
    }
}
