//! The print's imperfections: rough edges (each printed circle's radius perturbed as a
//! function of angle, seeded per target and edge) and uneven ink (a low-frequency density
//! variation over the board). Both are fixed to the board: every frame sees the same print.

use crate::camera::CameraModel;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::f64::consts::TAU;

/// Samples of a rough edge around the circle.
const EDGE_SAMPLES: usize = 1024;

/// SplitMix64 finaliser (seeds for independent streams).
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The radius error of one printed circle as a function of angle, µm.
#[derive(Debug, Clone, PartialEq)]
pub struct RoughEdge {
    table: Vec<f32>,
}

impl RoughEdge {
    /// The edge of circle `edge` (0 outer hole, 1 outer rim, 2 inner rim, 3 inner hole) of
    /// target `target` with radius `radius_um`: white noise around the circle smoothed by a
    /// Gaussian of `edge_roughness_corr_um` arc length, scaled to `edge_roughness_um` RMS.
    /// `None` when the camera's print has no roughness.
    pub fn new(cam: &CameraModel, target: usize, edge: usize, radius_um: f64) -> Option<RoughEdge> {
        if cam.edge_roughness_um == 0.0 || radius_um <= 0.0 {
            return None;
        }
        let seed = mix(mix(cam.print_seed) ^ ((target as u64) << 8 | edge as u64));
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let white: Vec<f64> = (0..EDGE_SAMPLES)
            .map(|_| StandardNormal.sample(&mut rng))
            .collect();
        let arc_um = TAU * radius_um / EDGE_SAMPLES as f64;
        let sigma = cam.edge_roughness_corr_um / arc_um;
        let reach = ((4.0 * sigma).ceil() as usize).min(EDGE_SAMPLES / 2);
        let kernel: Vec<f64> = (0..=reach)
            .map(|k| (-0.5 * (k as f64 / sigma.max(1e-9)).powi(2)).exp())
            .collect();
        let n = EDGE_SAMPLES;
        let smooth: Vec<f64> = (0..n)
            .map(|i| {
                let mut s = kernel[0] * white[i];
                for (k, w) in kernel.iter().enumerate().skip(1) {
                    s += w * (white[(i + k) % n] + white[(i + n - k % n) % n]);
                }
                s
            })
            .collect();
        let rms = (smooth.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
        let scale = cam.edge_roughness_um / rms.max(1e-300);
        Some(RoughEdge {
            table: smooth.iter().map(|v| (v * scale) as f32).collect(),
        })
    }

    /// Radius error (µm) in the direction `(dx, dy)` from the circle's centre.
    #[inline]
    pub fn at(&self, dx: f64, dy: f64) -> f64 {
        let turns = dy.atan2(dx) / TAU;
        let x = (turns - turns.floor()) * EDGE_SAMPLES as f64;
        let i = x as usize % EDGE_SAMPLES;
        let f = x - x.floor();
        let a = self.table[i] as f64;
        let b = self.table[(i + 1) % EDGE_SAMPLES] as f64;
        a + (b - a) * f
    }

    /// How far the least-squares circle through this edge lies from the designed centre,
    /// µm: the radius error's first harmonic, `(2/N)·Σ δ·(cos θ, sin θ)`.
    pub fn centre_shift_um(&self) -> [f64; 2] {
        let n = self.table.len() as f64;
        let (mut x, mut y) = (0.0, 0.0);
        for (i, &d) in self.table.iter().enumerate() {
            let (sn, cs) = (TAU * i as f64 / n).sin_cos();
            x += d as f64 * cs;
            y += d as f64 * sn;
        }
        [2.0 * x / n, 2.0 * y / n]
    }

    /// The tabulated samples (µm), counter-clockwise in image axes from +x.
    pub fn samples(&self) -> &[f32] {
        &self.table
    }
}

/// The ink's relative density over the board: `1 + ε(p)`, ε a sum of random plane waves
/// with a Gaussian spectrum (correlation length `ink_density_corr_um`), RMS `ink_density_rms`.
#[derive(Debug, Clone, PartialEq)]
pub struct InkDensity {
    waves: Vec<([f64; 2], f64)>,
    amplitude: f64,
}

impl InkDensity {
    const WAVES: usize = 12;

    pub fn new(cam: &CameraModel) -> Option<InkDensity> {
        if cam.ink_density_rms == 0.0 {
            return None;
        }
        let mut rng = ChaCha8Rng::seed_from_u64(mix(cam.print_seed ^ 0x0069_6e6b));
        let k = 1.0 / cam.ink_density_corr_um;
        let waves = (0..Self::WAVES)
            .map(|_| {
                let kx: f64 = StandardNormal.sample(&mut rng);
                let ky: f64 = StandardNormal.sample(&mut rng);
                ([kx * k, ky * k], rng.gen::<f64>() * TAU)
            })
            .collect();
        Some(InkDensity {
            waves,
            amplitude: cam.ink_density_rms * (2.0 / Self::WAVES as f64).sqrt(),
        })
    }

    /// ε blurred by a Gaussian PSF of variance `var_px2` about the image point that sees
    /// board point `p_um` (`jt`: Jᵀ, J the board µm per image px there), with its image
    /// gradient and Hessian (xx, xy, yy): each plane wave blurs to itself times
    /// `exp(−σ²|k|²/2)`, exactly. The renderer blurs the inked density whole from them
    /// (`warp::InkTaylor`).
    pub fn blurred(
        &self,
        p_um: [f64; 2],
        jt: [[f64; 2]; 2],
        var_px2: f64,
    ) -> (f64, [f64; 2], [f64; 3]) {
        let (mut e, mut g, mut h) = (0.0, [0.0; 2], [0.0; 3]);
        for (k, ph) in &self.waves {
            let ki = [
                jt[0][0] * k[0] + jt[0][1] * k[1],
                jt[1][0] * k[0] + jt[1][1] * k[1],
            ];
            let damp = self.amplitude * (-0.5 * var_px2 * (ki[0] * ki[0] + ki[1] * ki[1])).exp();
            let (sn, cs) = (k[0] * p_um[0] + k[1] * p_um[1] + ph).sin_cos();
            let (s, c) = (damp * sn, damp * cs);
            e += c;
            g = [g[0] - s * ki[0], g[1] - s * ki[1]];
            h = [
                h[0] - c * ki[0] * ki[0],
                h[1] - c * ki[0] * ki[1],
                h[2] - c * ki[1] * ki[1],
            ];
        }
        (e, g, h)
    }

    /// ε at board point `p_um`.
    #[inline]
    pub fn at(&self, p_um: [f64; 2]) -> f64 {
        self.amplitude
            * self
                .waves
                .iter()
                .map(|(k, ph)| (k[0] * p_um[0] + k[1] * p_um[1] + ph).cos())
                .sum::<f64>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rough_edge_has_the_rms_and_is_seeded_per_edge() {
        let cam = CameraModel {
            edge_roughness_um: 10.0,
            ..CameraModel::default()
        };
        let e = RoughEdge::new(&cam, 3, 1, 17_000.0).unwrap();
        let rms = (e.samples().iter().map(|&v| (v as f64).powi(2)).sum::<f64>() / 1024.0).sqrt();
        assert!((rms - 10.0).abs() < 1e-3, "{rms}");
        assert_eq!(Some(e.clone()), RoughEdge::new(&cam, 3, 1, 17_000.0));
        assert_ne!(Some(e.clone()), RoughEdge::new(&cam, 3, 0, 17_000.0));
        assert_ne!(Some(e), RoughEdge::new(&cam, 4, 1, 17_000.0));
        assert!(RoughEdge::new(&CameraModel::default(), 3, 1, 17_000.0).is_none());
    }

    /// The printed edge's own centre is the least-squares circle through it: fitted
    /// independently (x² + y² + D·x + E·y + F = 0 by least squares, over the edge's points
    /// as `at` gives them) it lies where `centre_shift_um` says, to 0.1 µm on a 5 mm circle
    /// whose edge is 10 µm rough.
    #[test]
    fn a_rough_edges_centre_is_its_least_squares_circles() {
        let cam = CameraModel {
            edge_roughness_um: 10.0,
            ..CameraModel::default()
        };
        let r = 5_000.0;
        for target in 0..4 {
            let e = RoughEdge::new(&cam, target, 2, r).unwrap();
            let pts: Vec<[f64; 2]> = (0..720)
                .map(|i| {
                    let (sn, cs) = (TAU * (i as f64 + 0.5) / 720.0).sin_cos();
                    let rho = r + e.at(cs, sn);
                    [rho * cs, rho * sn]
                })
                .collect();
            let a = nalgebra::DMatrix::from_fn(pts.len(), 3, |i, j| [pts[i][0], pts[i][1], 1.0][j]);
            let b = nalgebra::DVector::from_iterator(
                pts.len(),
                pts.iter().map(|p| -(p[0] * p[0] + p[1] * p[1])),
            );
            let sol = a.svd(true, true).solve(&b, 1e-12).unwrap();
            let fitted = [-sol[0] / 2.0, -sol[1] / 2.0];
            let said = e.centre_shift_um();
            assert!(
                (fitted[0] - said[0]).hypot(fitted[1] - said[1]) < 0.1
                    && said[0].hypot(said[1]) > 0.2,
                "fitted {fitted:?}, said {said:?}"
            );
        }
    }

    #[test]
    fn ink_density_has_about_the_rms() {
        let cam = CameraModel {
            ink_density_rms: 0.05,
            ink_density_corr_um: 1000.0,
            ..CameraModel::default()
        };
        let d = InkDensity::new(&cam).unwrap();
        let n = 200;
        let ms = (0..n * n)
            .map(|i| {
                d.at([(i % n) as f64 * 997.0, (i / n) as f64 * 1013.0])
                    .powi(2)
            })
            .sum::<f64>()
            / (n * n) as f64;
        assert!((ms.sqrt() - 0.05).abs() < 0.01, "{}", ms.sqrt());
    }
}
