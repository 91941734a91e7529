//! The Cramér–Rao bound on a target's measured offset, from the renderer itself.
//!
//! The Fisher information of one frame's pixels about the parameters θ of what is rendered:
//! `F = Σ_pixels Σ_channels ∂μ/∂θ ∂μ/∂θᵀ / var(μ)`, with μ the expected DN from
//! `render::expected_rgb` (derivatives by central differences of real renders, so the bound
//! holds for exactly what the simulator draws, pixel area integration and all) and var(μ)
//! from `CameraModel::noise_var_dn2` (shot + read + quantisation noise). θ holds the
//! quantity of interest, both centres, and the nuisance parameters an estimator does not
//! know: the ring's and the inner shape's radii, the lens blur, the illumination level,
//! gradient and vignetting, and the ink's reflectance in each channel used. The bound on the
//! offset (inner minus outer centre) is `eᵀF⁻¹e` per axis.
//!
//! The signal-dependence of the noise variance also carries (a little) information; it is
//! left out, so this is the bound for estimators that treat the noise as a known-variance
//! Gaussian, which is what a least-squares fit is.

use crate::board::{Board, Shape};
use crate::camera::CameraModel;
use crate::render::{expected_rgb, View};
use nalgebra::{DMatrix, DVector};

/// What one parameter of θ changes, and by how much for the central difference.
#[derive(Debug, Clone, Copy)]
enum Param {
    OuterX,
    OuterY,
    InnerX,
    InnerY,
    /// Radius `i` of the outer ring (0 = hole, 1 = rim) or of the inner shape (2 = rim, 3 = hole).
    Radius(usize),
    Blur,
    Light,
    Gradient,
    Vignetting,
    Ink(usize),
}

/// One-sigma bound on the offset (inner minus outer centre) of target `target_index`, in µm
/// on the board, x and y, for an estimator that uses only the measurement channel (the one
/// with the most ink-to-paper contrast, as rigd picks it).
pub fn offset_crb_um(
    board: &Board,
    cam: &CameraModel,
    target_index: usize,
    view: View,
) -> [f64; 2] {
    let ch = measurement_channel(board);
    offset_crb_um_channels(board, cam, target_index, view, &[ch])
}

/// The channel with the most ink-to-paper contrast.
pub fn measurement_channel(board: &Board) -> usize {
    (0..3)
        .max_by(|&a, &b| {
            let ca = (board.paper_rgb[a] - board.ink_rgb[a]).abs();
            let cb = (board.paper_rgb[b] - board.ink_rgb[b]).abs();
            ca.total_cmp(&cb)
        })
        .unwrap_or(1)
}

/// The bound for an estimator that uses the given channels (0 = R, 1 = G, 2 = B).
///
/// # Panics
/// If `target_index` is not a target of `board` or a channel is not 0..3 (caller errors).
pub fn offset_crb_um_channels(
    board: &Board,
    cam: &CameraModel,
    target_index: usize,
    view: View,
    channels: &[usize],
) -> [f64; 2] {
    assert!(channels.iter().all(|&c| c < 3), "channels must be 0..3");
    let observe = |rgb: &[f32], _roi: [u32; 4]| -> Vec<f64> {
        rgb.iter()
            .enumerate()
            .filter(|(i, _)| channels.contains(&(i % 3)))
            .map(|(_, &v)| v as f64)
            .collect()
    };
    let var = |m: f64| cam.noise_var_dn2(m);
    offset_crb(board, cam, target_index, view, channels, &observe, &var)
}

/// The bound from the sensor's own samples, before any processing: one Bayer sample per
/// pixel (with the camera's colour crosstalk) for an RGGB sensor, all three channels
/// otherwise; shot and read noise, quantisation of the 10-bit raw. Whatever the camera does
/// afterwards (demosaicing, gamma, sharpening, MJPEG) only loses information, so this bounds
/// every estimator working on the delivered frames, for any camera profile. The lens
/// (tilt, distortion, lateral colour) and the print's roughness are rendered but taken as
/// known (not nuisance parameters): the bound is for an estimator that knows its lens.
pub fn offset_crb_um_raw(
    board: &Board,
    cam: &CameraModel,
    target_index: usize,
    view: View,
) -> [f64; 2] {
    let bayer = crate::isp::bayer(cam);
    let c = cam.crosstalk as f32;
    let observe = |rgb: &[f32], roi: [u32; 4]| -> Vec<f64> {
        if !bayer {
            return rgb.iter().map(|&v| v as f64).collect();
        }
        let [x0, y0, w, _] = roi;
        rgb.chunks(3)
            .enumerate()
            .map(|(i, p)| {
                let (x, y) = (x0 as usize + i % w as usize, y0 as usize + i / w as usize);
                crate::isp::mixed(p, crate::isp::cfa_channel(x, y), c) as f64
            })
            .collect()
    };
    let q = (crate::isp::RAW_STEP_DN as f64).powi(2) / 12.0;
    let var = |m: f64| cam.noise_var_dn2(m) - 1.0 / 12.0 + q;
    offset_crb(board, cam, target_index, view, &[0, 1, 2], &observe, &var)
}

/// What an estimator sees of a rendered ROI (RGB f32, its box): the samples it gets.
type Observe<'a> = dyn Fn(&[f32], [u32; 4]) -> Vec<f64> + 'a;

/// The bound for samples `observe(rendered RGB of the ROI, roi)` with noise variance
/// `var(expected sample)`; `channels` are the ink reflectances taken as unknown.
#[allow(clippy::too_many_arguments)]
fn offset_crb(
    board: &Board,
    cam: &CameraModel,
    target_index: usize,
    view: View,
    channels: &[usize],
    observe: &Observe,
    var: &dyn Fn(f64) -> f64,
) -> [f64; 2] {
    let target = &board.targets[target_index];
    // Render only this target, in a window that holds all of its blurred edges.
    let mut base = board.clone();
    base.targets = vec![target.clone()];
    base.clutter.clear();
    let (c, grow) = if cam.needs_warp() {
        let lens = crate::optics::Lens::new(cam);
        (
            view.project(cam, 1, target.centre_um),
            lens.max_scale_ratio(cam),
        )
    } else {
        (view.board_to_image(cam, target.centre_um), 1.0)
    };
    let half = grow * target.outer.outer_radius_um() / cam.scale_um_per_px
        + 5.0 * cam.psf_sigma_px
        + 3.0
        + if grow > 1.0 { 2.0 } else { 0.0 };
    let x0 = (c[0] - half).floor().max(0.0) as u32;
    let y0 = (c[1] - half).floor().max(0.0) as u32;
    let x1 = ((c[0] + half).ceil() as u32).min(cam.width.saturating_sub(1));
    let y1 = ((c[1] + half).ceil() as u32).min(cam.height.saturating_sub(1));
    let roi = [x0, y0, x1 + 1 - x0, y1 + 1 - y0];

    let mut params = vec![
        Param::OuterX,
        Param::OuterY,
        Param::InnerX,
        Param::InnerY,
        Param::Radius(0),
        Param::Radius(1),
        Param::Radius(2),
    ];
    if matches!(target.inner, Shape::Ring { .. }) {
        params.push(Param::Radius(3));
    }
    params.extend([
        Param::Blur,
        Param::Light,
        Param::Gradient,
        Param::Vignetting,
    ]);
    params.extend(channels.iter().map(|&c| Param::Ink(c)));

    let render = |b: &Board, cm: &CameraModel, light: f64| expected_rgb(b, cm, &view, roi, light);
    let mu = observe(&render(&base, cam, 1.0), roi);
    let step_um = 0.02 * cam.scale_um_per_px;
    // Derivatives of every pixel's channels, per unit of each parameter (µm for lengths).
    let derivs: Vec<Vec<f64>> = params
        .iter()
        .map(|&p| {
            let (h, plus, minus) = perturb(&base, cam, p, step_um);
            let (lp, lm) = match p {
                Param::Light => (1.0 + h, 1.0 - h),
                _ => (1.0, 1.0),
            };
            let a = observe(&render(&plus.0, &plus.1, lp), roi);
            let b = observe(&render(&minus.0, &minus.1, lm), roi);
            a.iter()
                .zip(&b)
                .map(|(&a, &b)| (a - b) / (2.0 * h))
                .collect()
        })
        .collect();

    let n = params.len();
    let mut fisher = DMatrix::<f64>::zeros(n, n);
    let mut row = vec![0.0; n];
    for (i, &m) in mu.iter().enumerate() {
        let w = 1.0 / var(m);
        for (r, d) in row.iter_mut().zip(&derivs) {
            *r = d[i];
        }
        for a in 0..n {
            if row[a] == 0.0 {
                continue;
            }
            for b in a..n {
                fisher[(a, b)] += w * row[a] * row[b];
            }
        }
    }
    fisher.fill_lower_triangle_with_upper_triangle();
    let inv = fisher
        .clone()
        .cholesky()
        .map(|c| c.inverse())
        .expect("the Fisher information of a rendered target is positive definite");
    let var = |outer: usize, inner: usize| {
        let mut e = DVector::<f64>::zeros(n);
        e[outer] = -1.0;
        e[inner] = 1.0;
        (e.transpose() * &inv * &e)[(0, 0)]
    };
    [var(0, 2).sqrt(), var(1, 3).sqrt()]
}

/// The board and camera moved by +h and −h in parameter `p`, and h.
#[allow(clippy::type_complexity)]
fn perturb(
    board: &Board,
    cam: &CameraModel,
    p: Param,
    step_um: f64,
) -> (f64, (Board, CameraModel), (Board, CameraModel)) {
    let h = match p {
        Param::OuterX | Param::OuterY | Param::InnerX | Param::InnerY | Param::Radius(_) => step_um,
        Param::Blur => 0.01,
        Param::Light | Param::Gradient | Param::Vignetting | Param::Ink(_) => 1e-3,
    };
    let make = |sign: f64| {
        let mut b = board.clone();
        let mut c = cam.clone();
        let d = sign * h;
        let t = &mut b.targets[0];
        match p {
            // Move the outer shape only: the centre moves, the offset compensates.
            Param::OuterX => {
                t.centre_um[0] += d;
                t.offset_um[0] -= d;
            }
            Param::OuterY => {
                t.centre_um[1] += d;
                t.offset_um[1] -= d;
            }
            Param::InnerX => t.offset_um[0] += d,
            Param::InnerY => t.offset_um[1] += d,
            Param::Radius(i) => {
                let shape = if i < 2 { &mut t.outer } else { &mut t.inner };
                grow(shape, i, d);
            }
            Param::Blur => c.psf_sigma_px += d,
            Param::Light => {}
            Param::Gradient => c.light_gradient += d,
            Param::Vignetting => c.vignetting += d,
            Param::Ink(k) => b.ink_rgb[k] += d,
        }
        (b, c)
    };
    (h, make(1.0), make(-1.0))
}

/// Grow one radius of a shape: for the outer ring 0 = hole, 1 = rim; for the inner shape
/// 2 = rim (a disk's radius), 3 = an inner ring's hole.
fn grow(shape: &mut Shape, i: usize, d: f64) {
    match (shape, i) {
        (
            Shape::Ring {
                inner_radius_um, ..
            },
            0 | 3,
        ) => *inner_radius_um += d,
        (
            Shape::Ring {
                outer_radius_um, ..
            },
            1 | 2,
        ) => *outer_radius_um += d,
        (Shape::Disk { radius_um }, 2) => *radius_um += d,
        (s, i) => unreachable!("radius {i} of {s:?}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bound_is_microns_and_shrinks_with_less_noise() {
        let board = Board::paper();
        let cam = CameraModel::default();
        let view = View::at([0.3 * 774.0, 0.6 * 774.0]);
        let b = offset_crb_um(&board, &cam, 6, view);
        // Deterministic (expected values, no noise drawn): 3.44 µm per axis for one frame of
        // the paper's rig, green channel (docs/method.md). 5 % either way.
        let near = |v: f64, want: f64| (v / want - 1.0).abs() < 0.05;
        assert!(near(b[0], 3.44) && near(b[1], 3.44), "{b:?}");
        let quiet = CameraModel {
            gain_e_per_dn: 4.0 * cam.gain_e_per_dn,
            read_noise_dn: 0.0,
            ..cam.clone()
        };
        let q = offset_crb_um(&board, &quiet, 6, view);
        // 4x the gain halves a shot-noise-limited bound; no read noise takes it lower still:
        // 1.52 µm.
        assert!(near(q[0], 1.52) && q[0] < 0.5 * b[0], "{q:?} vs {b:?}");
        // All three channels know more than the best one alone: 2.48 µm.
        let all = offset_crb_um_channels(&board, &cam, 6, view, &[0, 1, 2]);
        eprintln!("CRB target A: green {b:?} µm, R+G+B {all:?} µm, 4x less noise {q:?} µm");
        assert!(near(all[0], 2.48) && all[0] < b[0], "{all:?} vs {b:?}");
    }
}
