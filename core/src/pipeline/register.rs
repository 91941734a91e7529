//! Registration: how far each frame's content moved from frame 0, three ways.
//!
//! - In the image (the paper's): the mean displacement of the targets' outer centres,
//!   each target matched to itself in frame 0.
//! - From positions, commanded steps or interferometer readings alike:
//!   `(position - position_0) / scale * axis_dir`. The camera rides the axis, so with the
//!   default `axis_dir = [-1, 0]` a +x move of the axis moves the scene -x in the image.
//!
//! Per step the two are compared ([`residuals`]): the image-minus-positions residual in µm
//! shows a stale frame, a missed step or a scale error at a glance.

use super::StepResidual;

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
        .map(|(index, (&p, &img))| {
            let pos = position_shift_px(p, p0, scale_um_per_px, axis_dir);
            StepResidual {
                index,
                position_um: p,
                image_shift_px: img,
                position_shift_px: pos,
                residual_um: [
                    (img[0] - pos[0]) * scale_um_per_px,
                    (img[1] - pos[1]) * scale_um_per_px,
                ],
            }
        })
        .collect()
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
}
