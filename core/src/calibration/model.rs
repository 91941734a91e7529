//! The field model: board plane (µm) -> image (px), a homography followed by Brown radial
//! distortion about the frame centre.
//!
//! `b` is a board point relative to the board point imaged at the frame centre, in the
//! board's axes (the print's when a board is given). The map:
//! `u = A b / (1 + g·b)` (px from the centre: a homography that sends 0 to the centre),
//! `x = c + u (1 + k1 ρ² + k2 ρ⁴)`, `ρ = |u| / norm_radius_px`.
//! The distortion centre is the frame centre, not fitted: a shift of it moves the image by
//! `2 k1 (u·δ) u / R²`, a scale changing linearly across the frame, which is what the
//! homography's perspective `g` already does, so the two cannot be told apart by a scan
//! and the homography absorbs a decentred lens.

use nalgebra::{Matrix2, Vector2};
use serde::{Deserialize, Serialize};

/// Points on a circle's image when its apparent centre is computed.
const CIRCLE_POINTS: usize = 96;

/// Names of the parameters [`FieldModel::params`] packs, in order.
pub const PARAM_NAMES: [&str; 8] = [
    "a00_px_per_um",
    "a01_px_per_um",
    "a10_px_per_um",
    "a11_px_per_um",
    "gx_per_um",
    "gy_per_um",
    "k1",
    "k2",
];

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FieldModel {
    /// Principal point and distortion centre: the frame centre (`(w - 1)/2, (h - 1)/2`).
    pub centre_px: [f64; 2],
    /// Radius normalising the distortion: the frame's half diagonal.
    pub norm_radius_px: f64,
    /// Linear part at the centre, px per µm (row-major).
    pub a_px_per_um: [[f64; 2]; 2],
    /// Perspective of a board off parallel, per µm.
    pub g_per_um: [f64; 2],
    pub k1: f64,
    pub k2: f64,
}

impl FieldModel {
    /// A model of a `w` x `h` frame: no tilt, no distortion, `scale_um_per_px` everywhere.
    pub fn plain(frame_size: (u32, u32), scale_um_per_px: f64) -> FieldModel {
        let (w, h) = (frame_size.0 as f64, frame_size.1 as f64);
        let s = 1.0 / scale_um_per_px;
        FieldModel {
            centre_px: [(w - 1.0) / 2.0, (h - 1.0) / 2.0],
            norm_radius_px: 0.5 * w.hypot(h),
            a_px_per_um: [[s, 0.0], [0.0, s]],
            g_per_um: [0.0; 2],
            k1: 0.0,
            k2: 0.0,
        }
    }

    /// The fitted parameters as one vector ([`PARAM_NAMES`]).
    pub fn params(&self) -> [f64; 8] {
        let a = self.a_px_per_um;
        let g = self.g_per_um;
        [
            a[0][0], a[0][1], a[1][0], a[1][1], g[0], g[1], self.k1, self.k2,
        ]
    }

    /// This model with the parameters `p` ([`FieldModel::params`]).
    pub fn with_params(&self, p: &[f64; 8]) -> FieldModel {
        FieldModel {
            a_px_per_um: [[p[0], p[1]], [p[2], p[3]]],
            g_per_um: [p[4], p[5]],
            k1: p[6],
            k2: p[7],
            ..self.clone()
        }
    }

    fn a(&self) -> Matrix2<f64> {
        let a = self.a_px_per_um;
        Matrix2::new(a[0][0], a[0][1], a[1][0], a[1][1])
    }

    /// Image point (px) of board point `b_um`.
    pub fn forward(&self, b_um: [f64; 2]) -> [f64; 2] {
        let b = Vector2::new(b_um[0], b_um[1]);
        let w = 1.0 + self.g_per_um[0] * b[0] + self.g_per_um[1] * b[1];
        let u = self.a() * b / w;
        let r2 = u.norm_squared() / (self.norm_radius_px * self.norm_radius_px);
        let f = 1.0 + self.k1 * r2 + self.k2 * r2 * r2;
        [self.centre_px[0] + u[0] * f, self.centre_px[1] + u[1] * f]
    }

    /// d(image px)/d(board µm) at `b_um` (central differences: the map is smooth on the
    /// scale of 10 µm, the error is ~1e-12 relative).
    pub fn jacobian(&self, b_um: [f64; 2]) -> Matrix2<f64> {
        let h = 10.0;
        let d = |i: usize| {
            let (mut p, mut m) = (b_um, b_um);
            p[i] += h;
            m[i] -= h;
            let (fp, fm) = (self.forward(p), self.forward(m));
            Vector2::new((fp[0] - fm[0]) / (2.0 * h), (fp[1] - fm[1]) / (2.0 * h))
        };
        Matrix2::from_columns(&[d(0), d(1)])
    }

    /// The board point imaged at `x_px` (Newton from the linear guess); `None` where the
    /// map folds over or does not converge.
    pub fn inverse(&self, x_px: [f64; 2]) -> Option<[f64; 2]> {
        let rel = Vector2::new(x_px[0] - self.centre_px[0], x_px[1] - self.centre_px[1]);
        let g = self.a().try_inverse()? * rel;
        let mut b = [g[0], g[1]];
        for _ in 0..30 {
            let f = self.forward(b);
            let r = Vector2::new(x_px[0] - f[0], x_px[1] - f[1]);
            let step = self.jacobian(b).try_inverse()? * r;
            b = [b[0] + step[0], b[1] + step[1]];
            if r.norm() < 1e-10 {
                return Some(b);
            }
        }
        let f = self.forward(b);
        ((x_px[0] - f[0]).hypot(x_px[1] - f[1]) < 1e-6).then_some(b)
    }

    /// Where the image of the circle of `radius_um` about `b_um` has its centre (the
    /// centroid of the region it bounds), minus the image of `b_um`: a tilted circle images
    /// as an ellipse whose centre is not the projected centre, and distortion adds to it.
    pub fn apparent_shift_px(&self, b_um: [f64; 2], radius_um: f64) -> [f64; 2] {
        let pts: Vec<[f64; 2]> = (0..CIRCLE_POINTS)
            .map(|i| {
                let t = std::f64::consts::TAU * i as f64 / CIRCLE_POINTS as f64;
                self.forward([b_um[0] + radius_um * t.cos(), b_um[1] + radius_um * t.sin()])
            })
            .collect();
        let c = polygon_centroid(&pts);
        let p = self.forward(b_um);
        [c[0] - p[0], c[1] - p[1]]
    }
}

/// Area centroid of a closed polygon (shoelace), taken about its first vertex so that the
/// small polygon far from the origin keeps its digits.
pub fn polygon_centroid(pts: &[[f64; 2]]) -> [f64; 2] {
    let o = pts[0];
    let (mut a, mut cx, mut cy) = (0.0, 0.0, 0.0);
    for i in 0..pts.len() {
        let p = [pts[i][0] - o[0], pts[i][1] - o[1]];
        let q = pts[(i + 1) % pts.len()];
        let q = [q[0] - o[0], q[1] - o[1]];
        let cross = p[0] * q[1] - q[0] * p[1];
        a += cross;
        cx += (p[0] + q[0]) * cross;
        cy += (p[1] + q[1]) * cross;
    }
    [o[0] + cx / (3.0 * a), o[1] + cy / (3.0 * a)]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tilted() -> FieldModel {
        let mut m = FieldModel::plain((1280, 720), 774.0);
        // tan(1.5°) / (1000 px · 774 µm/px): a board 1.5° off parallel seen with f = 1000 px.
        m.g_per_um = [0.0262 / 774_000.0, 0.0];
        m.k1 = -0.03;
        m
    }

    #[test]
    fn inverse_undoes_forward() {
        let m = tilted();
        for b in [[0.0, 0.0], [400_000.0, -250_000.0], [-480_000.0, 260_000.0]] {
            let x = m.forward(b);
            let back = m.inverse(x).unwrap();
            assert!((back[0] - b[0]).abs() < 1e-5 && (back[1] - b[1]).abs() < 1e-5);
        }
    }

    /// The ellipse's centre lies ~ tanθ r²/f towards the near side: 0.0262 · 19.4² / 1000 =
    /// 0.0099 px for a 15 mm circle at 774 µm/px (docs/sim.md, "Tilt").
    #[test]
    fn a_tilted_circle_images_off_its_projected_centre() {
        let m = FieldModel {
            k1: 0.0,
            ..tilted()
        };
        let s = m.apparent_shift_px([0.0, 0.0], 15_000.0);
        let want = -0.0262 * (15_000.0f64 / 774.0).powi(2) / 1000.0;
        assert!((s[0] - want).abs() < 0.05 * want.abs(), "{s:?} vs {want}");
        assert!(s[1].abs() < 1e-9, "{s:?}");
    }
}
