//! Lens and board geometry beyond the ideal parallel board: a board tilted against the
//! sensor (a homography), Brown radial distortion (k1, k2) and lateral colour (a magnification
//! per channel).
//!
//! Coordinates: `a_um` is a point of the board plane relative to the board point on the
//! optical axis (µm, x right, y down, in the camera's roll frame); image offsets are pixels
//! from the principal point (the frame centre). With no tilt, distortion or lateral colour the
//! map is `offset_px = a_um / scale_um_per_px`, the ideal camera's.

use crate::camera::CameraModel;
use nalgebra::{Matrix2, Matrix3, Vector3};

/// The camera's geometric model of one frame size (fixed to the camera: it does not move
/// with the line of sight).
#[derive(Debug, Clone)]
pub struct Lens {
    /// Board plane (a_x, a_y, 1) -> undistorted image (x, y, w), px.
    h: Matrix3<f64>,
    h_inv: Matrix3<f64>,
    focal_px: f64,
    k1: f64,
    k2: f64,
    /// Magnification of each channel's image relative to the distorted green image.
    mag: [f64; 3],
}

impl Lens {
    /// The lens of `cam`.
    pub fn new(cam: &CameraModel) -> Lens {
        Lens::at_depth(cam, 0.0)
    }

    /// The lens of `cam` with the board `depth_um` farther than at the rail's origin.
    pub fn at_depth(cam: &CameraModel, depth_um: f64) -> Lens {
        let f = cam.focal_length_px;
        let (tx, ty) = (cam.tilt_x_deg.to_radians(), cam.tilt_y_deg.to_radians());
        // The board's +x (+y) side recedes from the camera for a positive tilt about y (x).
        let ry = Matrix3::new(
            ty.cos(),
            0.0,
            -ty.sin(),
            0.0,
            1.0,
            0.0,
            ty.sin(),
            0.0,
            ty.cos(),
        );
        let rx = Matrix3::new(
            1.0,
            0.0,
            0.0,
            0.0,
            tx.cos(),
            -tx.sin(),
            0.0,
            tx.sin(),
            tx.cos(),
        );
        let r = ry * rx;
        // The board plane cuts the optical axis at a distance where 1 px at the centre is
        // scale_um_per_px (before the tilt's foreshortening).
        let z0 = f * cam.scale_um_per_px + depth_um;
        let k = Matrix3::new(f, 0.0, 0.0, 0.0, f, 0.0, 0.0, 0.0, 1.0);
        let rt = Matrix3::from_columns(&[
            r.column(0).into_owned(),
            r.column(1).into_owned(),
            Vector3::new(0.0, 0.0, z0),
        ]);
        let h = k * rt;
        let h_inv = h.try_inverse().expect("a tilt under 45° is invertible");
        Lens {
            h,
            h_inv,
            focal_px: f,
            k1: cam.distortion_k1,
            k2: cam.distortion_k2,
            mag: [1.0 + cam.lateral_colour_r, 1.0, 1.0 + cam.lateral_colour_b],
        }
    }

    /// Radial distortion factor at squared normalised radius `r2`.
    #[inline]
    fn radial(&self, r2: f64) -> f64 {
        1.0 + self.k1 * r2 + self.k2 * r2 * r2
    }

    /// Image offset (px from the principal point) of board-plane point `a_um` in `channel`.
    pub fn forward(&self, channel: usize, a_um: [f64; 2]) -> [f64; 2] {
        let p = self.h * Vector3::new(a_um[0], a_um[1], 1.0);
        let (xu, yu) = (p[0] / p[2], p[1] / p[2]);
        let r2 = (xu * xu + yu * yu) / (self.focal_px * self.focal_px);
        let g = self.radial(r2) * self.mag[channel];
        [xu * g, yu * g]
    }

    /// The undistorted image offset of distorted offset `d` (Newton on the radius).
    fn undistort(&self, d: [f64; 2]) -> [f64; 2] {
        let rd = (d[0] * d[0] + d[1] * d[1]).sqrt();
        if rd == 0.0 || (self.k1 == 0.0 && self.k2 == 0.0) {
            return d;
        }
        let f2 = self.focal_px * self.focal_px;
        let mut r = rd;
        for _ in 0..8 {
            let r2 = r * r / f2;
            let h = r * self.radial(r2) - rd;
            let dh = 1.0 + 3.0 * self.k1 * r2 + 5.0 * self.k2 * r2 * r2;
            let step = h / dh;
            r -= step;
            if step.abs() < 1e-12 * rd {
                break;
            }
        }
        let s = r / rd;
        [d[0] * s, d[1] * s]
    }

    /// The board-plane point seen at image offset `off_px` in `channel`, and the Jacobian
    /// d(a_um)/d(offset_px) there (µm per px, row-major).
    pub fn inverse(&self, channel: usize, off_px: [f64; 2]) -> ([f64; 2], Matrix2<f64>) {
        let m = self.mag[channel];
        let u = self.undistort([off_px[0] / m, off_px[1] / m]);
        let q = self.h_inv * Vector3::new(u[0], u[1], 1.0);
        let a = [q[0] / q[2], q[1] / q[2]];
        (
            a,
            self.jacobian_forward(channel, a)
                .try_inverse()
                .unwrap_or(Matrix2::zeros()),
        )
    }

    /// d(offset_px)/d(a_um) at board-plane point `a_um` (analytic).
    pub fn jacobian_forward(&self, channel: usize, a_um: [f64; 2]) -> Matrix2<f64> {
        let h = &self.h;
        let p = h * Vector3::new(a_um[0], a_um[1], 1.0);
        let w = p[2];
        let (xu, yu) = (p[0] / w, p[1] / w);
        // Homography: d(xu, yu)/d(a).
        let jh = Matrix2::new(
            (h[(0, 0)] - xu * h[(2, 0)]) / w,
            (h[(0, 1)] - xu * h[(2, 1)]) / w,
            (h[(1, 0)] - yu * h[(2, 0)]) / w,
            (h[(1, 1)] - yu * h[(2, 1)]) / w,
        );
        // Distortion: x_d = x_u·g(r²), r² = |x_u|²/f².
        let f2 = self.focal_px * self.focal_px;
        let r2 = (xu * xu + yu * yu) / f2;
        let g = self.radial(r2);
        let dg = (self.k1 + 2.0 * self.k2 * r2) * 2.0 / f2;
        let jd = Matrix2::new(
            g + xu * dg * xu,
            xu * dg * yu,
            yu * dg * xu,
            g + yu * dg * yu,
        );
        jd * jh * self.mag[channel]
    }

    /// The largest local scale (px per µm) anywhere in a `w`x`h` frame, relative to the
    /// centre's: boxes around shapes grow by it.
    pub fn max_scale_ratio(&self, cam: &CameraModel) -> f64 {
        let (cx, cy) = (cam.width as f64 / 2.0, cam.height as f64 / 2.0);
        let centre = self.jacobian_forward(1, [0.0, 0.0]).norm();
        let mut worst: f64 = 1.0;
        for &(x, y) in &[(-cx, -cy), (cx, -cy), (-cx, cy), (cx, cy), (0.0, 0.0)] {
            let (a, _) = self.inverse(1, [x, y]);
            for ch in 0..3 {
                worst = worst.max(self.jacobian_forward(ch, a).norm() / centre);
            }
        }
        worst
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> CameraModel {
        CameraModel {
            tilt_x_deg: 1.0,
            tilt_y_deg: -2.0,
            distortion_k1: -0.05,
            distortion_k2: 0.01,
            lateral_colour_r: 5e-4,
            lateral_colour_b: -5e-4,
            ..CameraModel::default()
        }
    }

    #[test]
    fn inverse_undoes_forward_and_the_jacobian_is_the_derivative() {
        let lens = Lens::new(&cam());
        for &(x, y) in &[(0.0, 0.0), (600.0, -350.0), (-630.0, 340.0), (100.0, 7.0)] {
            for ch in 0..3 {
                let (a, j) = lens.inverse(ch, [x, y]);
                let b = lens.forward(ch, a);
                assert!((b[0] - x).abs() < 1e-8 && (b[1] - y).abs() < 1e-8, "{b:?}");
                // Finite differences of the inverse.
                let h = 1e-3;
                let (ax, _) = lens.inverse(ch, [x + h, y]);
                let (ay, _) = lens.inverse(ch, [x, y + h]);
                let num = Matrix2::new(
                    (ax[0] - a[0]) / h,
                    (ay[0] - a[0]) / h,
                    (ax[1] - a[1]) / h,
                    (ay[1] - a[1]) / h,
                );
                assert!((num - j).norm() / j.norm() < 1e-5, "{num} vs {j}");
            }
        }
    }

    #[test]
    fn an_ideal_lens_is_the_plain_scale() {
        let c = CameraModel::default();
        let lens = Lens::new(&c);
        let p = lens.forward(1, [774.0 * 3.5, -774.0 * 2.0]);
        assert!(
            (p[0] - 3.5).abs() < 1e-12 && (p[1] + 2.0).abs() < 1e-12,
            "{p:?}"
        );
    }

    /// A rail along the sensor takes a board tilted 1.5° about y 20 mm × tan 1.5° farther
    /// after 20 mm of travel along x: the image shrinks by that over the distance; a rail
    /// along the board changes nothing.
    #[test]
    fn a_rail_along_the_sensor_zooms_a_tilted_board_over_the_travel() {
        use crate::render::View;
        let mut c = CameraModel {
            tilt_y_deg: 1.5,
            ..CameraModel::default()
        };
        let spread = |c: &CameraModel, travel: f64| {
            let v = View::on_rail(c, [0.0, 0.0], [travel, 0.0]);
            let (a, b) = (
                v.project(c, 1, [travel, 0.0]),
                v.project(c, 1, [travel, 300_000.0]),
            );
            (b[1] - a[1]).abs()
        };
        let still = spread(&c, 20_000.0) / spread(&c, 0.0);
        assert!((still - 1.0).abs() < 1e-9, "{still}");
        c.rail_along_sensor = 1.0;
        let (board, depth) = c.rail_pose([20_000.0, 0.0]);
        let t = 1.5f64.to_radians();
        assert!((depth - 20_000.0 * t.tan()).abs() < 1e-9, "{depth}");
        assert!((board[0] - 20_000.0 / t.cos()).abs() < 1e-9, "{board:?}");
        let z0 = c.focal_length_px * c.scale_um_per_px;
        let zoom = spread(&c, 20_000.0) / spread(&c, 0.0);
        assert!(
            (zoom - z0 / (z0 + depth)).abs() < 2e-5,
            "{zoom} vs {}",
            z0 / (z0 + depth)
        );
    }
}
