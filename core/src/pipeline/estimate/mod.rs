//! Centre estimators: from the pixels of one target to its outer and inner centres.
//!
//! - `paper`: what the paper did, centroids of the thresholded ring and disk regions.
//! - `fit` (the default): a least-squares fit of a blurred ring-and-disk model, with the
//!   offset's covariance from the fit.
//!
//! Both work on the pixels within the guessed outer rim plus a margin for the blur; the
//! guess (from `detect`, or a registered first frame) only has to be good to a pixel or so.

mod fit;
mod paper;

pub use fit::{
    bumps_at, DensitySample, InkMean, InkShape, PlaneInk, DENSITY_EDGE_MARGIN_S,
    DENSITY_READ_MARGIN_S, PRIOR_PEAK_BYTES,
};

use super::accumulate::Lattice;
use super::detect::{Candidate, Detection};
use super::plane::Plane;
use super::Estimator;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CentreEstimate {
    pub outer_px: [f64; 2],
    pub inner_px: [f64; 2],
    /// Rim radius of the outer ring.
    pub outer_radius_px: f64,
    /// Rim radius of the inner disk (or ring).
    pub inner_radius_px: f64,
    /// Covariance of `offset_px()` (fit only).
    pub offset_cov_px2: Option<[[f64; 2]; 2]>,
    /// The fit's whole state, to start a later fit of the same target from (fit only; not
    /// part of any output).
    #[serde(skip)]
    pub seed: Option<Seed>,
    /// When the fit freed the contrast planes (uneven ink), what the even-ink model gave on
    /// the same pixels: how far the ink model moved the offset, and how much less noisy the
    /// simpler model is (fit only; not part of any output).
    #[serde(skip)]
    pub even_ink: Option<EvenInk>,
}

/// The even-ink model's offset and covariance, beside a fit that chose the planes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EvenInk {
    pub offset_px: [f64; 2],
    pub offset_cov_px2: Option<[[f64; 2]; 2]>,
}

/// A fit's whole state (centres, radii, blur, levels, contrasts, and which model it chose),
/// in the pixels of the plane it was fitted on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Seed(fit::State);

impl Seed {
    /// The same state in another plane's pixels: `to` maps a point, lengths scale by `k`.
    pub fn mapped(&self, to: impl Fn([f64; 2]) -> [f64; 2], k: f64) -> Seed {
        Seed(self.0.mapped(to, k))
    }

    /// The same fit with the even-ink model (registration's: a displacement does not see
    /// the print's own bias, and the four contrast gradients would add ~40 % of scatter).
    pub fn even_ink(&self) -> Seed {
        Seed(self.0.even_ink())
    }

    /// The fit's blur width, in its plane's pixels.
    pub fn blur_px(&self) -> f64 {
        self.0.blur_px()
    }
}

/// Where a fit starts from. A start near the minimum saves most of the passes over the
/// pixels (a fit from the guess takes five or more, a seeded one one or two); the minimum
/// it converges to is the same to 1e-4 px.
#[derive(Debug, Clone, Copy, Default)]
pub enum Start<'a> {
    /// From the guess: its centres and radii, levels from the window.
    #[default]
    Guess,
    /// From an earlier fit of the same target in this plane's pixels, choosing the ink
    /// model anew (a reconstruction, with less noise than the frame the seed came from).
    Near(&'a Seed),
    /// From an earlier fit of the same target, keeping its ink model (the same print in a
    /// later frame: registration's per-frame fits).
    Track(&'a Seed),
}

impl CentreEstimate {
    /// Inner centre minus outer centre.
    pub fn offset_px(&self) -> [f64; 2] {
        [
            self.inner_px[0] - self.outer_px[0],
            self.inner_px[1] - self.outer_px[1],
        ]
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EstimateError {
    #[error("bad guess: {0}")]
    BadGuess(String),
    #[error(
        "the target's window (x {x0:.0}..{x1:.0}, y {y0:.0}..{y1:.0}) is outside the {width}x{height} plane"
    )]
    RoiOutside {
        x0: f64,
        x1: f64,
        y0: f64,
        y1: f64,
        width: usize,
        height: usize,
    },
    #[error("no ink in the window around ({x:.1}, {y:.1}): {what}")]
    NoInk { x: f64, y: f64, what: String },
    #[error("fit diverged after {iterations} iterations: {reason}")]
    Diverged { iterations: usize, reason: String },
}

/// Estimate the centres of one target in `plane` (the measurement channel).
///
/// `guess` is in `plane`'s own pixel coordinates (the caller shifts it for a crop and scales
/// it for a k-times finer reconstruction); `px_per_camera_px` is k (1 for a raw frame) so
/// priors such as the blur width scale with the grid.
pub fn estimate(
    plane: &Plane,
    guess: &Candidate,
    estimator: Estimator,
    px_per_camera_px: f64,
) -> Result<CentreEstimate, EstimateError> {
    estimate_from(
        plane,
        guess,
        estimator,
        px_per_camera_px,
        Start::Guess,
        None,
    )
}

/// [`estimate`] with the fit started at `start` and, with `ink`, the print's density as a
/// prior (the paper estimator ignores both). The window and the checks still come from
/// `guess`.
pub fn estimate_from(
    plane: &Plane,
    guess: &Candidate,
    estimator: Estimator,
    px_per_camera_px: f64,
    start: Start,
    ink: Option<PlaneInk>,
) -> Result<CentreEstimate, EstimateError> {
    let k = px_per_camera_px;
    if !(k.is_finite() && k > 0.0) {
        return Err(EstimateError::BadGuess(format!(
            "px_per_camera_px must be positive, got {k}"
        )));
    }
    check_guess(guess)?;
    let win = Window::around(plane, guess, k)?;
    match estimator {
        Estimator::Paper => paper::estimate(plane, &win, guess),
        Estimator::Fit => fit::estimate(plane, &win, guess, k, start, ink),
    }
}

/// The print's ink density inside the shapes of the fit `seed` of `guess` on `plane`
/// (`px_per_camera_px` = k), as its residuals say it ([`DensitySample`]): what a
/// calibration scan learns the print's statistics from.
pub fn ink_density(
    plane: &Plane,
    guess: &Candidate,
    px_per_camera_px: f64,
    seed: &Seed,
) -> Result<Vec<DensitySample>, EstimateError> {
    check_guess(guess)?;
    let win = Window::around(plane, guess, px_per_camera_px)?;
    Ok(fit::density(plane, &win, guess, px_per_camera_px, &seed.0))
}

/// The only pixels of a reconstruction that `estimator` reads when it measures `guess` on
/// it (`px_per_camera_px` = k): every `step`-th one in x and y from the window's origin, for
/// the fit. `None` when it reads every pixel (the paper's estimator, or k < 2). A
/// reconstruction needs to compute no others ([`Lattice`]).
pub fn lattice_read(
    estimator: Estimator,
    guess: &Candidate,
    px_per_camera_px: f64,
) -> Option<Lattice> {
    let step = match estimator {
        Estimator::Fit => fit::sample_step(px_per_camera_px),
        Estimator::Paper => 1,
    };
    let origin = Window::origin(guess, px_per_camera_px);
    (step > 1).then(|| Lattice {
        step,
        phase: origin.map(|o| o % step),
    })
}

/// Measure every detected target of a frame on the ROI path: each target's ROI of channel
/// `channel` only, in linear light through the camera's `response`, estimated in parallel.
/// Results in frame coordinates, in `det`'s order.
pub fn estimate_targets(
    img: &image::RgbImage,
    det: &Detection,
    (channel, response): (usize, super::Response),
    estimator: Estimator,
) -> Vec<Result<CentreEstimate, EstimateError>> {
    use rayon::prelude::*;
    det.targets
        .par_iter()
        .map(|c| {
            let plane = Plane::from_channel_roi_in(img, channel, c.roi, response);
            let origin = [c.roi.x as f64, c.roi.y as f64];
            let e = estimate(
                &plane,
                &c.translated([-origin[0], -origin[1]]),
                estimator,
                1.0,
            )?;
            let mv = |p: [f64; 2]| [p[0] + origin[0], p[1] + origin[1]];
            Ok(CentreEstimate {
                outer_px: mv(e.outer_px),
                inner_px: mv(e.inner_px),
                seed: e.seed.map(|s| s.mapped(mv, 1.0)),
                ..e
            })
        })
        .collect()
}

fn check_guess(g: &Candidate) -> Result<(), EstimateError> {
    let finite = g
        .outer_centre_px
        .iter()
        .chain(&g.inner_centre_px)
        .chain(&g.outer_radii_px)
        .chain(&g.inner_radii_px)
        .all(|v| v.is_finite());
    if !finite {
        return Err(EstimateError::BadGuess(format!(
            "non-finite centre or radius in {g:?}"
        )));
    }
    let [hole, rim] = g.outer_radii_px;
    let [ih, ir] = g.inner_radii_px;
    if !(hole > 0.0 && rim > hole && ir > 0.0 && ih >= 0.0 && ih < ir) {
        return Err(EstimateError::BadGuess(format!(
            "radii must satisfy 0 < hole < rim and 0 <= inner hole < inner rim: outer {:?}, inner {:?}",
            g.outer_radii_px, g.inner_radii_px
        )));
    }
    Ok(())
}

/// The pixels an estimator looks at: a square around the guessed outer centre reaching the
/// rim plus a margin for the blur, clipped to the plane.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Window {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize, // exclusive
    pub y1: usize,
    /// Pixels farther than this from the guessed outer centre are ignored (clutter).
    pub reach: f64,
}

impl Window {
    /// The window's first column and row for guess `g` on a `k`-times finer grid.
    fn origin(g: &Candidate, k: f64) -> [usize; 2] {
        let want = g.outer_radii_px[1] + 3.5 * k;
        g.outer_centre_px
            .map(|c| (c - want).floor().max(0.0) as usize)
    }

    fn around(plane: &Plane, g: &Candidate, k: f64) -> Result<Window, EstimateError> {
        let c = g.outer_centre_px;
        let rim = g.outer_radii_px[1];
        let want = rim + 3.5 * k;
        let need = rim + 1.5 * k;
        let (w, h) = (plane.width as f64, plane.height as f64);
        let outside = c[0] - need < 0.0
            || c[1] - need < 0.0
            || c[0] + need > w - 1.0
            || c[1] + need > h - 1.0;
        if outside {
            return Err(EstimateError::RoiOutside {
                x0: c[0] - need,
                x1: c[0] + need,
                y0: c[1] - need,
                y1: c[1] + need,
                width: plane.width,
                height: plane.height,
            });
        }
        let [x0, y0] = Window::origin(g, k);
        let x1 = ((c[0] + want).ceil() as usize + 1).min(plane.width);
        let y1 = ((c[1] + want).ceil() as usize + 1).min(plane.height);
        Ok(Window {
            x0,
            y0,
            x1,
            y1,
            reach: want,
        })
    }

    /// Paper and ink levels: high and low percentiles of the window (ink covers a good part
    /// of it, paper most of the rest).
    pub fn levels(&self, plane: &Plane, step: usize) -> (f64, f64) {
        let step = step.max(1);
        // Selected as order-preserving integer keys: exact, and the comparisons in the
        // selection are plain integer ones (about twice as fast as `f32::total_cmp`, which
        // re-derives the key on every comparison; up to 3·10⁵ samples per fine grid).
        let mut v: Vec<u32> = Vec::with_capacity(
            (self.y1 - self.y0).div_ceil(step) * (self.x1 - self.x0).div_ceil(step),
        );
        for y in (self.y0..self.y1).step_by(step) {
            let row = &plane.data[y * plane.width + self.x0..y * plane.width + self.x1];
            v.extend(row.iter().step_by(step).map(|&x| f32_key(x)));
        }
        let n = v.len();
        let lo = n / 10;
        let hi = (n * 9 / 10).min(n - 1);
        let (_, &mut a, above) = v.select_nth_unstable(lo);
        // Everything past the lo-th is at least as large: the hi-th is among them.
        let b = match hi.checked_sub(lo + 1) {
            Some(i) => *above.select_nth_unstable(i).1,
            None => a,
        };
        (f32_from_key(b) as f64, f32_from_key(a) as f64)
    }
}

/// A u32 that orders as `f32::total_cmp` orders the floats.
fn f32_key(x: f32) -> u32 {
    let b = x.to_bits();
    if b >> 31 == 1 {
        !b
    } else {
        b | 0x8000_0000
    }
}

fn f32_from_key(k: u32) -> f32 {
    f32::from_bits(if k >> 31 == 1 { k & 0x7fff_ffff } else { !k })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A guess of a ring (`[hole, rim]`) around a disk, its ROI the whole n x n plane.
    fn whole_plane_guess(
        n: usize,
        (outer, inner): ([f64; 2], [f64; 2]),
        ring: [f64; 2],
        disk: f64,
    ) -> Candidate {
        Candidate {
            outer_centre_px: outer,
            inner_centre_px: inner,
            outer_radii_px: ring,
            inner_radii_px: [0.0, disk],
            roi: super::super::plane::Roi {
                x: 0,
                y: 0,
                w: n as u32,
                h: n as u32,
            },
            rectify: None,
        }
    }

    /// The fit on a k = 10 grid whose pixels off [`lattice_read`]'s lattice are NaN gives
    /// the very estimate it gives on the whole grid: it reads nothing else, so a
    /// reconstruction may compute nothing else.
    #[test]
    fn the_fit_reads_only_its_lattice() {
        let (n, k) = (200, 10.0);
        let (co, ci) = ([100.3, 99.6], [104.1, 98.2]);
        // A logistic edge (not the fit's erf) of ~0.5 camera px, a little pattern noise.
        let edge = |d: f64| 1.0 / (1.0 + (d / 3.0).exp());
        let mut plane = Plane::new(n, n);
        for (i, v) in plane.data.iter_mut().enumerate() {
            let (x, y) = ((i % n) as f64, (i / n) as f64);
            let ro = (x - co[0]).hypot(y - co[1]);
            let ri = (x - ci[0]).hypot(y - ci[1]);
            let cov = edge(ro - 70.0) - edge(ro - 50.0) + edge(ri - 25.0);
            *v = (200.0 - 150.0 * cov + 3.0 * ((i * 7919 % 101) as f64 / 101.0 - 0.5)) as f32;
        }
        let guess = whole_plane_guess(n, ([100.0, 100.0], [103.0, 99.0]), [50.0, 70.0], 25.0);
        let l = lattice_read(Estimator::Fit, &guess, k).expect("the fit strides on k = 10");
        assert_eq!(l.step, 5);
        assert_eq!(lattice_read(Estimator::Paper, &guess, k), None);
        let mut poisoned = plane.clone();
        for (i, v) in poisoned.data.iter_mut().enumerate() {
            let (x, y) = (i % n, i / n);
            if x % l.step != l.phase[0] || y % l.step != l.phase[1] {
                *v = f32::NAN;
            }
        }
        let whole = estimate_from(&plane, &guess, Estimator::Fit, k, Start::Guess, None).unwrap();
        let some = estimate_from(&poisoned, &guess, Estimator::Fit, k, Start::Guess, None).unwrap();
        assert_eq!(whole.offset_px(), some.offset_px());
        assert!(
            (whole.offset_px()[0] - 3.8).abs() < 0.05,
            "{:?}",
            whole.offset_px()
        );
    }

    /// ½·erfc(x/√2)-shaped edge (Abramowitz & Stegun 7.1.26, |error| < 1.5e-7).
    fn blurred_edge(d: f64, s: f64) -> f64 {
        let x = d / (s * std::f64::consts::SQRT_2);
        let t = 1.0 / (1.0 + 0.327_591_1 * x.abs());
        let poly = t
            * (0.254_829_592
                + t * (-0.284_496_736
                    + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
        let erfc = poly * (-x * x).exp();
        0.5 * if x >= 0.0 { erfc } else { 2.0 - erfc }
    }

    /// The blurred coverage (blur `s`) at `q` of a ring (`[hole, rim]`) about `co` and a
    /// disk about `ci`, and its gradient.
    fn coverage(
        q: [f64; 2],
        (co, ci): ([f64; 2], [f64; 2]),
        (ring, disk): ([f64; 2], f64),
        s: f64,
    ) -> (f64, [f64; 2]) {
        let slope = |d: f64| -(-d * d / (2.0 * s * s)).exp() / (s * (std::f64::consts::TAU).sqrt());
        let (mut cov, mut grad) = (0.0, [0.0; 2]);
        for (c, r, sign) in [(co, ring[1], 1.0), (co, ring[0], -1.0), (ci, disk, 1.0)] {
            let (dx, dy) = (q[0] - c[0], q[1] - c[1]);
            let rho = dx.hypot(dy).max(1e-9);
            cov += sign * blurred_edge(rho - r, s);
            let k = sign * slope(rho - r) / rho;
            grad = [grad[0] + k * dx, grad[1] + k * dy];
        }
        (cov, grad)
    }

    /// The inked density `(1 + ε)·f` blurred whole by a Gaussian of width `s`, to first
    /// order: `(1 + ε)·C + s²·∇ε·∇C` (what a lens does; the fit's model takes `(1 + ε)·C`).
    fn inked(eps: f64, grad: [f64; 2], (cov, cov_grad): (f64, [f64; 2]), s: f64) -> f64 {
        (1.0 + eps) * cov + s * s * (grad[0] * cov_grad[0] + grad[1] * cov_grad[1])
    }

    /// A ring and a disk printed each with its own linear density gradient (±14 % across
    /// a shape), seen through a lens that blurs the inked density whole: the blur moves
    /// each shape's edges by `s²·∇c/c`, 0.013 px apart between the two here. The fit with
    /// the contrast planes takes that back out of the centres. Measured: the offset is
    /// 0.0017 px off with the correction, 0.0117 px without; the fit alone, on the print
    /// drawn as its model draws it (the density times the blurred coverage), is 0.0017 px
    /// off too (0.0006 px on an even print).
    #[test]
    fn the_fit_takes_the_blur_of_a_linear_density_out_of_the_centres() {
        let n = 48;
        let (co, ci) = ([23.7, 24.2], [25.1, 23.4]);
        let guess = whole_plane_guess(n, ([24.0, 24.0], [25.0, 23.5]), [11.0, 14.0], 7.0);
        let (g_o, g_i) = ([0.01, 0.0], [-0.01, 0.005]);
        let s = 0.8;
        let mut plane = Plane::new(n, n);
        for (i, v) in plane.data.iter_mut().enumerate() {
            let q = [(i % n) as f64, (i / n) as f64];
            let outer = coverage(q, (co, ci), ([11.0, 14.0], 0.0), s);
            let inner = coverage(q, (co, ci), ([0.0, 0.0], 7.0), s);
            let eps = |g: [f64; 2], c: [f64; 2]| g[0] * (q[0] - c[0]) + g[1] * (q[1] - c[1]);
            let ink = inked(eps(g_o, co), g_o, outer, s) + inked(eps(g_i, ci), g_i, inner, s);
            *v = (200.0 * (1.0 - 0.6 * ink)) as f32;
        }
        let e = estimate_from(&plane, &guess, Estimator::Fit, 1.0, Start::Guess, None).unwrap();
        let o = e.offset_px();
        let err = (o[0] - (ci[0] - co[0])).hypot(o[1] - (ci[1] - co[1]));
        let shift = s * s * (g_i[0] - g_o[0]).hypot(g_i[1] - g_o[1]);
        assert!(
            err < 0.2 * shift,
            "offset {o:?}: {err:.5} px off, the blur's shift {shift:.4} px"
        );
    }

    /// Six waves of random direction and phase (`[kx, ky, phase]`), wavenumbers
    /// ~ N(0, 1/ℓ²) per axis: a print's uneven ink as the sim draws it.
    fn ink_waves(print: u64, corr_px: f64) -> Vec<[f64; 3]> {
        use std::f64::consts::TAU;
        let mut state = print * 7919 + 17;
        let mut rnd = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let g = |u: f64, v: f64| (-2.0 * u.max(1e-12).ln()).sqrt() * (TAU * v).cos();
        (0..6)
            .map(|_| {
                let (kx, ky) = (g(rnd(), rnd()) / corr_px, g(rnd(), rnd()) / corr_px);
                [kx, ky, TAU * rnd()]
            })
            .collect()
    }

    /// The waves' density and its gradient at (x, y), RMS `rms`.
    fn wave_density(waves: &[[f64; 3]], rms: f64, [x, y]: [f64; 2]) -> (f64, [f64; 2]) {
        let amp = rms * (2.0 / waves.len() as f64).sqrt();
        let (mut eps, mut grad) = (0.0, [0.0; 2]);
        for w in waves {
            let (sn, cs) = (w[0] * x + w[1] * y + w[2]).sin_cos();
            eps += amp * cs;
            grad = [grad[0] - amp * sn * w[0], grad[1] - amp * sn * w[1]];
        }
        (eps, grad)
    }

    /// A camera-scale target printed with uneven ink (4 % RMS over ~4 px, a few smooth
    /// waves as the sim draws it, blurred whole by the lens) and ±1 DN of pattern noise: the
    /// even-ink fit's offset is pulled by the density; the fit with the print's statistics
    /// as a prior takes most of that away; centred on the print's own density (as a
    /// calibration maps it), the prior takes more.
    #[test]
    fn the_ink_prior_takes_the_uneven_density_out_of_the_offset() {
        let n = 48;
        let (co, ci) = ([23.7, 24.2], [25.1, 23.4]);
        let guess = whole_plane_guess(n, ([24.0, 24.0], [25.0, 23.5]), [11.0, 14.0], 7.0);
        let truth = [ci[0] - co[0], ci[1] - co[1]];
        let ink = PlaneInk {
            density_rms: 0.04,
            corr_px: 3.9,
            mean: None,
        };
        let mut sq = [0.0; 3];
        for print in 0..8u64 {
            let waves = ink_waves(print, ink.corr_px);
            let mut plane = Plane::new(n, n);
            for (i, v) in plane.data.iter_mut().enumerate() {
                let (x, y) = ((i % n) as f64, (i / n) as f64);
                let (eps, grad) = wave_density(&waves, ink.density_rms, [x, y]);
                let (cov, cov_grad) = coverage([x, y], (co, ci), ([11.0, 14.0], 7.0), 0.8);
                let noise = ((i * 7919 % 101) as f64 / 101.0 - 0.5) * 2.0;
                *v = (200.0 * (1.0 - 0.6 * inked(eps, grad, (cov, cov_grad), 0.8)) + noise) as f32;
            }
            // The print's density as unit-spaced bumps 0.6 px wide about the outer centre
            // (it keeps 97 % of a wave at the print's ℓ).
            let w = 0.6;
            let bumps = (0..n * n)
                .map(|i| [(i % n) as f64, (i / n) as f64])
                .map(|[x, y]| {
                    let eps = wave_density(&waves, ink.density_rms, [x, y]).0;
                    [x - co[0], y - co[1], eps / (std::f64::consts::TAU * w * w)]
                })
                .collect();
            let mapped = PlaneInk {
                density_rms: 0.01,
                mean: Some(std::sync::Arc::new(InkMean { bumps, width_px: w })),
                ..ink.clone()
            };
            let fit = |ink| estimate_from(&plane, &guess, Estimator::Fit, 1.0, Start::Guess, ink);
            for (s, ink) in sq.iter_mut().zip([None, Some(ink.clone()), Some(mapped)]) {
                let o = fit(ink).unwrap().offset_px();
                *s += (o[0] - truth[0]).powi(2) + (o[1] - truth[1]).powi(2);
            }
        }
        let [even, prior, mapped] = sq.map(|s| (s / 16.0).sqrt());
        eprintln!(
            "RMS offset error per axis: even ink {even:.4} px, with the prior {prior:.4} px, \
             centred on the print's density {mapped:.4} px"
        );
        assert!(prior < 0.5 * even, "{prior:.4} vs {even:.4} px");
        assert!(mapped < 0.5 * prior, "{mapped:.4} vs {prior:.4} px");
    }

    /// The uneven-ink target of the test above imaged as ellipses 3.2 % out of round (a
    /// tilted board's corner, `Calibration::rectify_at`), the prior centred on the print's
    /// density: measured round, the misfit of the ellipses goes into the ink's modes and
    /// from them into the offset; measured as the ellipses they are (the guess's
    /// `rectify`), the offset is as good as on the round target.
    #[test]
    fn the_fit_measures_the_ellipses_a_calibration_says_the_circles_image_as() {
        let n = 48;
        let (co, ci) = ([23.7, 24.2], [25.1, 23.4]);
        let truth = [ci[0] - co[0], ci[1] - co[1]];
        // det 1: stretched 1.6 % along 30°, squeezed across it.
        let (sn, cs) = (30f64).to_radians().sin_cos();
        let (a, b) = (1.016, 1.0 / 1.016);
        let m = [
            [a * cs * cs + b * sn * sn, (a - b) * sn * cs],
            [(a - b) * sn * cs, a * sn * sn + b * cs * cs],
        ];
        let apply = |p: [f64; 2]| {
            [
                m[0][0] * p[0] + m[0][1] * p[1],
                m[1][0] * p[0] + m[1][1] * p[1],
            ]
        };
        let (rectify, w, rms) = (Some(m), 0.6, 0.04);
        let mut sq = [0.0; 2];
        for print in 0..8u64 {
            let waves = ink_waves(print, 3.9);
            let mut plane = Plane::new(n, n);
            for (i, v) in plane.data.iter_mut().enumerate() {
                let (x, y) = ((i % n) as f64, (i / n) as f64);
                let (eps, grad) = wave_density(&waves, rms, [x, y]);
                // The circles drawn in the rectified frame: an ellipse about each centre.
                let (cov, g) = coverage(
                    apply([x, y]),
                    (apply(co), apply(ci)),
                    ([11.0, 14.0], 7.0),
                    0.8,
                );
                let cov_grad = [
                    m[0][0] * g[0] + m[1][0] * g[1],
                    m[0][1] * g[0] + m[1][1] * g[1],
                ];
                let noise = ((i * 7919 % 101) as f64 / 101.0 - 0.5) * 2.0;
                *v = (200.0 * (1.0 - 0.6 * inked(eps, grad, (cov, cov_grad), 0.8)) + noise) as f32;
            }
            let bumps = (0..n * n)
                .map(|i| [(i % n) as f64, (i / n) as f64])
                .map(|[x, y]| {
                    let eps = wave_density(&waves, rms, [x, y]).0;
                    [x - co[0], y - co[1], eps / (std::f64::consts::TAU * w * w)]
                })
                .collect();
            let mapped = PlaneInk {
                density_rms: 0.01,
                corr_px: 3.9,
                mean: Some(std::sync::Arc::new(InkMean { bumps, width_px: w })),
            };
            for (s, rectify) in sq.iter_mut().zip([None, rectify]) {
                let guess = Candidate {
                    rectify,
                    ..whole_plane_guess(n, ([24.0, 24.0], [25.0, 23.5]), [11.0, 14.0], 7.0)
                };
                let ink = Some(mapped.clone());
                let e = estimate_from(&plane, &guess, Estimator::Fit, 1.0, Start::Guess, ink);
                let o = e.unwrap().offset_px();
                *s += (o[0] - truth[0]).powi(2) + (o[1] - truth[1]).powi(2);
            }
        }
        let [round, rectified] = sq.map(|s| (s / 16.0).sqrt());
        eprintln!("RMS offset error per axis: measured round {round:.4} px, as ellipses {rectified:.4} px");
        assert!(rectified < 0.5 * round, "{rectified:.4} vs {round:.4} px");
        assert!(rectified < 0.003, "{rectified:.4} px");
    }

    /// A rectifying map that only turns (a board turned in the image, no stretch) keeps
    /// distances: the fit, with the prior centred on the print's density, lands where it
    /// lands without one, to f32 rounding.
    #[test]
    fn a_rectifying_map_that_only_turns_changes_nothing() {
        let n = 48;
        let (co, ci) = ([23.7, 24.2], [25.1, 23.4]);
        let waves = ink_waves(3, 3.9);
        let mut plane = Plane::new(n, n);
        for (i, v) in plane.data.iter_mut().enumerate() {
            let (x, y) = ((i % n) as f64, (i / n) as f64);
            let (eps, grad) = wave_density(&waves, 0.04, [x, y]);
            let (cov, cov_grad) = coverage([x, y], (co, ci), ([11.0, 14.0], 7.0), 0.8);
            let noise = ((i * 7919 % 101) as f64 / 101.0 - 0.5) * 2.0;
            *v = (200.0 * (1.0 - 0.6 * inked(eps, grad, (cov, cov_grad), 0.8)) + noise) as f32;
        }
        let ink = Some(PlaneInk {
            density_rms: 0.04,
            corr_px: 3.9,
            mean: None,
        });
        let (sn, cs) = 0.7f64.sin_cos();
        let offsets = [None, Some([[cs, -sn], [sn, cs]])].map(|rectify| {
            let guess = Candidate {
                rectify,
                ..whole_plane_guess(n, ([24.0, 24.0], [25.0, 23.5]), [11.0, 14.0], 7.0)
            };
            let e = estimate_from(
                &plane,
                &guess,
                Estimator::Fit,
                1.0,
                Start::Guess,
                ink.clone(),
            );
            e.unwrap().offset_px()
        });
        let d = (offsets[0][0] - offsets[1][0]).hypot(offsets[0][1] - offsets[1][1]);
        assert!(d < 1e-4, "{offsets:?}");
    }

    /// A target many correlation lengths wide (rim 80 px, the print's ℓ 4 px): the prior's
    /// grid and samples are capped (bounded memory and time), and the fit still lands on
    /// the offset of an evenly printed target.
    #[test]
    fn the_ink_prior_on_a_large_target_is_bounded_and_right() {
        let n = 200;
        let (co, ci) = ([100.4, 99.7], [103.2, 98.1]);
        let mut plane = Plane::new(n, n);
        for (i, v) in plane.data.iter_mut().enumerate() {
            let (x, y) = ((i % n) as f64, (i / n) as f64);
            let e = |d: f64| blurred_edge(d, 0.8);
            let ro = (x - co[0]).hypot(y - co[1]);
            let cov = e(ro - 80.0) - e(ro - 70.0) + e((x - ci[0]).hypot(y - ci[1]) - 40.0);
            let noise = ((i * 7919 % 101) as f64 / 101.0 - 0.5) * 2.0;
            *v = (200.0 * (1.0 - 0.6 * cov) + noise) as f32;
        }
        let guess = whole_plane_guess(n, ([100.0, 100.0], [103.0, 98.0]), [70.0, 80.0], 40.0);
        let ink = Some(PlaneInk {
            density_rms: 0.04,
            corr_px: 4.0,
            mean: None,
        });
        let e = estimate_from(&plane, &guess, Estimator::Fit, 1.0, Start::Guess, ink).unwrap();
        let o = e.offset_px();
        assert!(
            (o[0] - 2.8).abs() < 0.01 && (o[1] + 1.6).abs() < 0.01,
            "{o:?}"
        );
    }

    #[test]
    fn keys_order_as_total_cmp_and_come_back_exactly() {
        let xs = [
            -300.5f32,
            -1.0,
            -f32::MIN_POSITIVE,
            -0.0,
            0.0,
            f32::MIN_POSITIVE,
            0.25,
            1.0,
            254.99,
            255.0,
            1e30,
        ];
        for (i, &a) in xs.iter().enumerate() {
            assert_eq!(f32_from_key(f32_key(a)).to_bits(), a.to_bits());
            for &b in &xs[i + 1..] {
                assert!(f32_key(a) < f32_key(b), "{a} vs {b}");
            }
        }
    }

    #[test]
    fn levels_are_the_10th_and_90th_percentiles() {
        // A 40x30 plane of scrambled values, some negative (cubic overshoot).
        let mut plane = Plane::new(40, 30);
        for (i, v) in plane.data.iter_mut().enumerate() {
            *v = ((i * 7919) % 1201) as f32 * 0.25 - 20.0;
        }
        let win = Window {
            x0: 3,
            y0: 2,
            x1: 37,
            y1: 29,
            reach: f64::INFINITY,
        };
        let mut want: Vec<f32> = (2..29)
            .flat_map(|y| (3..37).map(move |x| (x, y)))
            .map(|(x, y)| plane.data[y * 40 + x])
            .collect();
        want.sort_by(f32::total_cmp);
        let n = want.len();
        let (paper, ink) = win.levels(&plane, 1);
        assert_eq!(ink, want[n / 10] as f64);
        assert_eq!(paper, want[n * 9 / 10] as f64);
    }
}
