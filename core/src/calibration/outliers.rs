//! Outliers, rejected before the field is fitted and after: a centre far off its own
//! target's line (a missed or stale frame, a mis-detection in one frame), and a target far
//! off the field model (a misprint, a target the board names wrongly, one half out of
//! view). Both thresholds are robust (the median absolute deviation), so one bad point
//! cannot hide itself by inflating the scatter it is judged against; every rejection is
//! kept in the record with its residual.

use super::fit::line_fit;
use super::scan::Scan;
use serde::{Deserialize, Serialize};

/// A centre is an outlier beyond this many robust σ of the scan's line residuals.
pub const POINT_SIGMAS: f64 = 5.0;
/// A target is an outlier when its RMS residual against the field model is beyond this
/// many times the median target's.
pub const TARGET_FACTOR: f64 = 3.0;
/// The smallest residual (px) ever called an outlier: on nearly noiseless centres (the
/// ideal camera's ~0.005 px) the leadscrew's periodic error and the lens' curvature of a
/// track are not outliers.
pub const FLOOR_PX: f64 = 0.05;

/// One centre or target left out of the fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Rejected {
    /// The target's index in the scan, and its board name.
    pub target_index: usize,
    pub target: Option<String>,
    /// The frame, for a single centre; `None` for a whole target.
    pub step: Option<usize>,
    /// Its residual (a centre's against its line, a target's RMS against the model), px.
    pub residual_px: f64,
    pub reason: String,
}

/// `1.4826 · median |x|`: the σ of a normal sample, robust to a few outliers.
fn robust_sigma(abs: &mut [f64]) -> Option<f64> {
    if abs.is_empty() {
        return None;
    }
    abs.sort_by(f64::total_cmp);
    Some(1.4826 * abs[abs.len() / 2])
}

/// The scan without the centres beyond [`POINT_SIGMAS`] robust σ of their target's line
/// (σ pooled over every target and axis), and what was taken out.
pub(crate) fn reject_points(scan: &Scan, min_steps: usize, piezo: bool) -> (Scan, Vec<Rejected>) {
    let mut abs: Vec<f64> = (0..scan.targets.len())
        .filter_map(|t| line_fit(scan, t, min_steps, piezo))
        .flat_map(|l| l.residuals_px.into_iter())
        .flat_map(|(_, r)| [r[0].abs(), r[1].abs()])
        .collect();
    let Some(sigma) = robust_sigma(&mut abs) else {
        return (scan.clone(), Vec::new());
    };
    let limit = (POINT_SIGMAS * sigma).max(FLOOR_PX);
    let mut clean = scan.clone();
    let mut rejected = Vec::new();
    for t in 0..scan.targets.len() {
        // The worst centre first, the line refitted after each: a wild centre pulls its
        // line and with it its neighbours' residuals.
        while let Some(line) = line_fit(&clean, t, min_steps, piezo) {
            let worst = line
                .residuals_px
                .iter()
                .map(|&(i, r)| (i, r[0].hypot(r[1])))
                .max_by(|a, b| a.1.total_cmp(&b.1));
            let Some((i, off)) = worst.filter(|w| w.1 > limit) else {
                break;
            };
            clean.targets[t].centres_px[i] = None;
            rejected.push(Rejected {
                target_index: t,
                target: scan.targets[t].name.clone(),
                step: Some(i),
                residual_px: off,
                reason: format!(
                    "{off:.3} px off its line, beyond {POINT_SIGMAS} robust σ ({limit:.3} px)"
                ),
            });
        }
    }
    (clean, rejected)
}

/// Of the fitted targets' RMS residuals against the model (px), the worst if it is beyond
/// [`TARGET_FACTOR`] times the median, with the reason. One at a time: a misprinted target
/// pulls the model and with it every other target's residual.
pub(crate) fn worst_target(rms_px: &[f64]) -> Option<(usize, String)> {
    let mut sorted = rms_px.to_vec();
    sorted.sort_by(f64::total_cmp);
    let median = *sorted.get(sorted.len() / 2)?;
    let limit = (TARGET_FACTOR * median).max(FLOOR_PX);
    let (j, &r) = rms_px
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))?;
    (r > limit).then(|| {
        let why = format!(
            "RMS {r:.3} px off the field model, beyond {TARGET_FACTOR}x the median target's ({limit:.3} px)"
        );
        (j, why)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_target_far_off_the_model_is_flagged_and_the_rest_are_not() {
        let rms = [0.02, 0.03, 0.025, 0.4, 0.028];
        let (j, why) = worst_target(&rms).unwrap();
        assert_eq!(j, 3);
        assert!(why.contains("0.400 px"), "{why}");
        assert_eq!(worst_target(&[0.02, 0.03, 0.025, 0.028]), None);
    }

    #[test]
    fn residuals_below_the_floor_are_never_outliers() {
        // Tiny residuals, one 10x the others but under FLOOR_PX.
        assert_eq!(worst_target(&[0.001, 0.001, 0.01, 0.001]), None);
    }

    #[test]
    fn robust_sigma_ignores_one_wild_value() {
        let mut v = vec![1.0, 1.0, 1.0, 1.0, 100.0];
        assert_eq!(robust_sigma(&mut v), Some(1.4826));
        assert_eq!(robust_sigma(&mut []), None);
    }
}
