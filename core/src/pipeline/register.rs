//! Registration: how far each frame's content moved from frame 0, three ways.
//!
//! - In the image (the paper's): the mean displacement of the targets' outer centres,
//!   each target matched to itself in frame 0.
//! - From positions, commanded steps or interferometer readings alike:
//!   `(position - position_0) / scale * axis_dir`. The camera rides the axis, so with the
//!   default `axis_dir = [-1, 0]` a +x move of the axis moves the scene -x in the image.
//!   A run that moves the piezo too (a 2-D grid, a list) adds
//!   `(piezo - piezo_0) / scale * piezo_dir` ([`Dirs`]).
//!
//! Per step the two are compared ([`residuals`]): the image-minus-positions residual in µm
//! shows a stale frame, a missed step or a scale error at a glance.

use super::{StepResidual, StepSummary};

/// Steps a result lists one by one; [`StepSummary`] covers every step.
pub const MAX_LISTED_STEPS: usize = 1000;

/// Displacement in px that the positions predict for a frame at `position_um`.
pub fn position_shift_px(
    position_um: f64,
    first_position_um: f64,
    scale_um_per_px: f64,
    axis_dir: [f64; 2],
) -> [f64; 2] {
    let t = (position_um - first_position_um) / scale_um_per_px;
    [t * axis_dir[0], t * axis_dir[1]]
}

/// How a run's positions move the image: px per px of travel of its stage and, in a run
/// that moves the piezo too, of the piezo.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dirs {
    pub scale_um_per_px: f64,
    pub axis_dir: [f64; 2],
    pub piezo_dir: [f64; 2],
}

/// Where a frame was taken: its stage's position and the piezo's (0 when the run moves one
/// stage only).
pub type At = [f64; 2];

impl Dirs {
    /// Displacement in px the positions predict for a frame at `at` (stage, piezo).
    pub fn shift_px(&self, at: At, first: At) -> [f64; 2] {
        let a = (at[0] - first[0]) / self.scale_um_per_px;
        let p = (at[1] - first[1]) / self.scale_um_per_px;
        [
            a * self.axis_dir[0] + p * self.piezo_dir[0],
            a * self.axis_dir[1] + p * self.piezo_dir[1],
        ]
    }
}

/// Mean displacement of the targets measured in both frames: `pairs` holds
/// `(centre in frame 0, centre in this frame)` for each target found in both.
/// `None` when no target is.
pub fn image_shift_px(pairs: &[([f64; 2], [f64; 2])]) -> Option<[f64; 2]> {
    if pairs.is_empty() {
        return None;
    }
    let n = pairs.len() as f64;
    let (sx, sy) = pairs.iter().fold((0.0, 0.0), |(sx, sy), (a, b)| {
        (sx + b[0] - a[0], sy + b[1] - a[1])
    });
    Some([sx / n, sy / n])
}

/// One step's image displacement against the positions' prediction.
pub fn residual(
    index: usize,
    position_um: f64,
    first_position_um: f64,
    image_shift_px: [f64; 2],
    scale_um_per_px: f64,
    axis_dir: [f64; 2],
) -> StepResidual {
    let pos = position_shift_px(position_um, first_position_um, scale_um_per_px, axis_dir);
    StepResidual {
        index,
        position_um,
        piezo_um: None,
        image_shift_px,
        position_shift_px: pos,
        residual_um: [
            (image_shift_px[0] - pos[0]) * scale_um_per_px,
            (image_shift_px[1] - pos[1]) * scale_um_per_px,
        ],
    }
}

/// [`residual`] of a frame taken at `at` (stage, piezo) in a run that starts at `first`;
/// `piezo`: whether the run moves the piezo (its position is then listed).
pub fn residual_at(
    index: usize,
    (at, first): (At, At),
    image_shift_px: [f64; 2],
    dirs: &Dirs,
    piezo: bool,
) -> StepResidual {
    let pos = dirs.shift_px(at, first);
    let s = dirs.scale_um_per_px;
    StepResidual {
        index,
        position_um: at[0],
        piezo_um: piezo.then_some(at[1]),
        image_shift_px,
        position_shift_px: pos,
        residual_um: [
            (image_shift_px[0] - pos[0]) * s,
            (image_shift_px[1] - pos[1]) * s,
        ],
    }
}

/// Per step: image displacement against the positions' prediction.
pub fn residuals(
    positions_um: &[f64],
    image_shifts_px: &[[f64; 2]],
    scale_um_per_px: f64,
    axis_dir: [f64; 2],
) -> Vec<StepResidual> {
    let p0 = positions_um.first().copied().unwrap_or(0.0);
    positions_um
        .iter()
        .zip(image_shifts_px)
        .enumerate()
        .map(|(index, (&p, &img))| residual(index, p, p0, img, scale_um_per_px, axis_dir))
        .collect()
}

/// The residuals of a run as its frames arrive: the first [`MAX_LISTED_STEPS`] listed, every
/// one summarised, so a run's length does not grow its result.
#[derive(Debug, Clone, Default)]
pub struct StepLog {
    listed: Vec<StepResidual>,
    summary: StepSummary,
    sum_sq_um2: [f64; 2],
}

impl StepLog {
    pub fn push(&mut self, r: StepResidual) {
        let s = &mut self.summary;
        s.frames += 1;
        for (q, x) in self.sum_sq_um2.iter_mut().zip(r.residual_um) {
            *q += x * x;
        }
        let size = |r: &StepResidual| r.residual_um[0].hypot(r.residual_um[1]);
        if s.largest.as_ref().is_none_or(|l| size(&r) > size(l)) {
            s.largest = Some(r.clone());
        }
        if self.listed.len() < MAX_LISTED_STEPS {
            self.listed.push(r);
        }
    }

    /// (the listed steps, the summary of all).
    pub fn finish(self) -> (Vec<StepResidual>, StepSummary) {
        let mut s = self.summary;
        let n = s.frames.max(1) as f64;
        s.rms_residual_um = self.sum_sq_um2.map(|q| (q / n).sqrt());
        (self.listed, s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_moving_plus_x_moves_the_scene_minus_x() {
        let s = position_shift_px(1774.0, 1000.0, 774.0, [-1.0, 0.0]);
        assert!((s[0] + 1.0).abs() < 1e-12 && s[1] == 0.0);
    }

    #[test]
    fn a_piezo_move_adds_its_own_direction() {
        let d = Dirs {
            scale_um_per_px: 100.0,
            axis_dir: [-1.0, 0.0],
            piezo_dir: [0.0, -1.0],
        };
        let s = d.shift_px([1050.0, 30.0], [1000.0, 10.0]);
        assert!(
            (s[0] + 0.5).abs() < 1e-12 && (s[1] + 0.2).abs() < 1e-12,
            "{s:?}"
        );
        let r = residual_at(3, ([1050.0, 30.0], [1000.0, 10.0]), [-0.5, -0.1], &d, true);
        assert_eq!(r.piezo_um, Some(30.0));
        assert!((r.residual_um[1] - 10.0).abs() < 1e-9 && r.residual_um[0].abs() < 1e-9);
    }

    #[test]
    fn image_shift_is_the_mean_of_the_target_moves() {
        let pairs = [([10.0, 20.0], [9.9, 20.0]), ([100.0, 50.0], [99.7, 50.2])];
        let s = image_shift_px(&pairs).unwrap();
        assert!((s[0] + 0.2).abs() < 1e-12 && (s[1] - 0.1).abs() < 1e-12);
        assert!(image_shift_px(&[]).is_none());
    }

    #[test]
    fn residual_is_image_minus_positions_in_um() {
        let r = residuals(
            &[0.0, 50.0],
            &[[0.0, 0.0], [-0.07, 0.01]],
            774.0,
            [-1.0, 0.0],
        );
        assert_eq!(r.len(), 2);
        let want_x = (-0.07 + 50.0 / 774.0) * 774.0;
        assert!((r[1].residual_um[0] - want_x).abs() < 1e-9);
        assert!((r[1].residual_um[1] - 7.74).abs() < 1e-9);
        assert_eq!(r[1].position_um, 50.0);
    }

    #[test]
    fn the_step_log_lists_a_bounded_number_and_summarises_all() {
        let mut log = StepLog::default();
        let n = MAX_LISTED_STEPS + 500;
        for i in 0..n {
            // A stale frame past the listed ones: 50 µm off on x, the rest 0.774 µm on y.
            let img = if i == n - 3 {
                [0.0, 0.001]
            } else {
                [-(i as f64) * 50.0 / 774.0, 0.001]
            };
            log.push(residual(i, 50.0 * i as f64, 0.0, img, 774.0, [-1.0, 0.0]));
        }
        let (listed, s) = log.finish();
        assert_eq!(listed.len(), MAX_LISTED_STEPS);
        assert_eq!(listed[MAX_LISTED_STEPS - 1].index, MAX_LISTED_STEPS - 1);
        assert_eq!(s.frames, n);
        let largest = s.largest.clone().unwrap();
        assert_eq!(largest.index, n - 3);
        assert!((largest.residual_um[0] - 50.0 * (n - 3) as f64).abs() < 1e-6);
        // y: 0.774 µm on every step.
        assert!((s.rms_residual_um[1] - 0.774).abs() < 1e-9, "{s:?}");
    }
}
