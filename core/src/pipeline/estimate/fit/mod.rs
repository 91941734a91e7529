//! The model fit: Levenberg–Marquardt least squares of a blurred ring-and-disk image to the
//! window's pixels.
//!
//! Model of pixel (x, y): `I = L(x, y) · (1 − c_o(x, y) · cov_o(x, y) − c_i(x, y) ·
//! cov_i(x, y))` with
//! - `L = b0 + bx·X + by·Y`, the paper level as a plane (vignetting and uneven light are
//!   smooth over one target), X and Y the position in the window scaled to about ±1;
//! - `c_o`, `c_i` the ink contrast (1 − ink/paper) of the outer ring and of the inner shape,
//!   each a plane `c + cx·X + cy·Y` of its own: printed ink is not evenly dense, and a
//!   contrast that changes across a shape moves its fitted edges (by ~√π·s·Δc/c: 50 µm per
//!   4 % on a webcam frame) unless the model lets it change;
//! - `cov_o`, `cov_i` the ink coverage of each shape: a sum of blurred circle edges, each
//!   `E(ρ − R) = ½·erfc((ρ − R)/(√2·s))` of the signed distance to the circle, + for the
//!   rims, − for the holes. One blur width `s` stands for the lens blur and the pixel's own
//!   area (their variances add: s² ≈ σ_psf² + 1/12 px²).
//!
//! The parameters: both centres, all radii, `s`, `b0`, `bx`, `by` and the two contrast
//! planes (17, 18 with an inner ring). The offset's covariance is the inner-minus-outer
//! block of `(JᵀJ)⁻¹ · σ̂²`, with σ̂² the residual variance.

use super::{CentreEstimate, EstimateError, Window};
use crate::pipeline::detect::Candidate;
use crate::pipeline::plane::Plane;
use nalgebra::{DMatrix, DVector};

mod blur_shift;
mod density;
mod edge;
mod normal;
mod prior;

pub use density::{
    DensitySample, InkShape, EDGE_MARGIN_S as DENSITY_EDGE_MARGIN_S,
    READ_MARGIN_S as DENSITY_READ_MARGIN_S,
};
pub use prior::{bumps_at, InkMean, PlaneInk, PEAK_BYTES as PRIOR_PEAK_BYTES};

use normal::Normal;

const CXO: usize = 0;
const CYO: usize = 1;
const HOLE: usize = 2;
const RIM: usize = 3;
const CXI: usize = 4;
const CYI: usize = 5;
const RI: usize = 6;
const S: usize = 7;
const B0: usize = 8;
const BX: usize = 9;
const BY: usize = 10;
/// The ink contrast of each shape, a plane `c + cx·X + cy·Y`: the outer ring's
/// coefficients from `C` on, the inner shape's from `CI`. (A cubic contrast, or one field
/// for both shapes, did not do better on uneven ink: `tests/webcam_accuracy.rs`.)
const C: usize = 11;
const NC: usize = 3;
const CI: usize = C + NC;
/// Hole of an inner ring (absent for an inner disk).
const RIH: usize = CI + NC;
const MAXP: usize = RIH + 1;
/// The contrast planes' gradients.
const GRADIENTS: [usize; 4] = [C + 1, C + 2, CI + 1, CI + 2];
/// Uneven ink enters the model only where the data show it: the gradients' score statistic
/// (χ², 4 degrees of freedom) above its 99.9 % point. On evenly printed targets the four
/// parameters would only add scatter (~40 % on the offset).
const GRADIENTS_CHI2: f64 = 18.47;

const MAX_ITER: usize = 60;
/// A step shorter than 0.1 σ of the parameters (in Mahalanobis distance, squared) is the
/// last one.
const SHORT_STEP_SIGMAS2: f64 = 1e-2;
struct Problem<'a> {
    plane: &'a Plane,
    win: &'a Window,
    np: usize,
    /// Pixel stride in x and y.
    step: usize,
    /// Window centre and half size for the background plane's X, Y.
    mid: [f64; 2],
    inv_half: f64,
    reach_centre: [f64; 2],
    /// Whether the contrast planes' gradients are free (else held at 0).
    planes: bool,
    /// Image offsets to offsets in which the target's circles are circles (det 1,
    /// row-major; the identity unless the guess knows the local shape).
    rectify: [[f64; 2]; 2],
}

impl<'a> Problem<'a> {
    /// The even-ink model of `np` parameters of the target guessed at `g`, read every
    /// `step`-th pixel of `win`.
    fn new(plane: &'a Plane, win: &'a Window, g: &Candidate, step: usize, np: usize) -> Self {
        let half = 0.5 * (win.x1 - win.x0).max(win.y1 - win.y0) as f64;
        Problem {
            plane,
            win,
            np,
            step,
            mid: [
                0.5 * (win.x0 + win.x1 - 1) as f64,
                0.5 * (win.y0 + win.y1 - 1) as f64,
            ],
            inv_half: 1.0 / half.max(1.0),
            reach_centre: g.outer_centre_px,
            planes: false,
            rectify: g.rectify.unwrap_or([[1.0, 0.0], [0.0, 1.0]]),
        }
    }

    /// Distance of offset (`dx`, `dy`) from a centre in the rectified frame, and its
    /// derivatives with respect to the centre: an edge's distance `ρ − R` measures the
    /// imaged ellipse, not a circle.
    #[inline(always)]
    fn rho<T: edge::Real>(&self, dx: T, dy: T) -> (T, T, T) {
        let c = T::c;
        let [[a, b], [cc, d]] = self.rectify;
        let (u, v) = (c(a) * dx + c(b) * dy, c(cc) * dx + c(d) * dy);
        let r = (u * u + v * v).sqrt().max(c(1e-9));
        let inv = c(1.0) / r;
        // dρ/dcx = −(Aᵀ·u)_x / ρ.
        (
            r,
            -(c(a) * u + c(cc) * v) * inv,
            -(c(b) * u + c(d) * v) * inv,
        )
    }

    /// `JᵀJ`, with a unit diagonal for the held gradients (their steps are then 0).
    fn matrix(&self, n: &Normal) -> DMatrix<f64> {
        DMatrix::from_fn(self.np, self.np, |a, b| {
            if a == b && !self.planes && GRADIENTS.contains(&a) {
                1.0
            } else {
                n.h[a][b]
            }
        })
    }

    /// Parameters the fit moves.
    fn free(&self) -> usize {
        if self.planes {
            self.np
        } else {
            self.np - GRADIENTS.len()
        }
    }
}

/// A converged fit's whole state, to start a later fit of the same target from (see
/// [`super::Start`]): the parameters in the plane's pixels of that fit and whether the
/// contrast planes were free.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct State {
    p: [f64; MAXP],
    np: usize,
    planes: bool,
}

impl State {
    /// The same state in other coordinates: `to` maps a point (both centres), lengths (radii,
    /// blur) scale by `k`. Levels and contrasts are the same in any grid.
    pub fn mapped(&self, to: impl Fn([f64; 2]) -> [f64; 2], k: f64) -> State {
        let mut p = self.p;
        [p[CXO], p[CYO]] = to([p[CXO], p[CYO]]);
        [p[CXI], p[CYI]] = to([p[CXI], p[CYI]]);
        for i in [HOLE, RIM, RI, S, RIH] {
            p[i] *= k;
        }
        State { p, ..*self }
    }

    pub fn blur_px(&self) -> f64 {
        self.p[S]
    }

    /// The even-ink model's state: the contrast gradients held at 0.
    pub fn even_ink(&self) -> State {
        let mut p = self.p;
        for i in GRADIENTS {
            p[i] = 0.0;
        }
        State {
            p,
            planes: false,
            ..*self
        }
    }
}

/// The fit reads every `sample_step(k)`-th pixel of a `k`-times finer grid in x and y.
/// On such a grid (a reconstruction) neighbouring pixels are interpolated from the same
/// camera pixels: every ⌊k/2⌋-th one (2 per camera pixel, above the Nyquist rate of an edge
/// blurred by ~1 px) carries the information at a 25th of the cost. (Against every
/// ⌊k/3⌋-th, the paper study's std on k = 5 and 10 reconstructions is 1.1 and 0.8 µm, was
/// 1.2 and 0.9; the webcam study's is unchanged.)
pub(super) fn sample_step(k: f64) -> usize {
    ((k / 2.0).floor() as usize).max(1)
}

pub(super) fn estimate(
    plane: &Plane,
    win: &Window,
    g: &Candidate,
    k: f64,
    start: super::Start,
    ink: Option<PlaneInk>,
) -> Result<CentreEstimate, EstimateError> {
    let step = sample_step(k);
    let (paper, ink_level) = win.levels(plane, step);
    if paper - ink_level < 4.0 || paper <= 0.0 {
        return Err(EstimateError::NoInk {
            x: g.outer_centre_px[0],
            y: g.outer_centre_px[1],
            what: format!("no contrast between paper ({paper:.1} DN) and ink ({ink_level:.1} DN)"),
        });
    }
    let ring_inner = g.inner_radii_px[0] > 0.0;
    let np = if ring_inner { MAXP } else { MAXP - 1 };
    let prob = Problem::new(plane, win, g, step, np);
    let uneven = Problem {
        planes: true,
        ..prob
    };
    let seed = match start {
        super::Start::Guess => None,
        super::Start::Near(s) | super::Start::Track(s) => Some(s.0).filter(|s| s.np == np),
    };
    if let Some(ink) = ink {
        return with_prior(&prob, (seed, start), (g, k, paper, ink_level), ink);
    }
    match (seed, start) {
        // The same target a moment later: its ink has not changed, nor has the model.
        (Some(s), super::Start::Track(_)) => {
            let model = if s.planes { &uneven } else { &prob };
            Ok(solve(model, s.p, k, g, Steps::FirstIfNear, None)?.estimate(model))
        }
        _ => {
            // (The even-ink model holds the gradients where they start: at 0.)
            let p = seed.map_or_else(|| first_guess(g, k, paper, ink_level), |s| s.even_ink().p);
            // The even-ink model first (as fast as a fit without the planes); the planes
            // only when a score test at its minimum shows uneven ink: one more pass on
            // evenly printed targets.
            let even = solve(&prob, p, k, g, Steps::ToMinimum, Some(&uneven))?;
            if !uneven_ink_shows(&prob, &uneven, &even) {
                return Ok(even.estimate(&prob));
            }
            let mut p = even.p;
            if let Some(s) = seed.filter(|s| s.planes) {
                // Start the gradients where the seed had them.
                for i in GRADIENTS {
                    p[i] = s.p[i];
                }
            }
            let mut est = solve(&uneven, p, k, g, Steps::ToMinimum, None)?.estimate(&uneven);
            let e = even.estimate(&prob);
            est.even_ink = Some(super::EvenInk {
                offset_px: e.offset_px(),
                offset_cov_px2: e.offset_cov_px2,
            });
            Ok(est)
        }
    }
}

/// The fit with the print's density as a prior ([`prior`]): the even-ink fit from the
/// start (one Gauss–Newton step when tracking), then the MAP fit from there. The offset's
/// covariance is the posterior's: the samples' noise and the print's unknown density.
fn with_prior(
    prob: &Problem,
    (seed, start): (Option<State>, super::Start),
    (g, k, paper, ink_level): (&Candidate, f64, f64, f64),
    ink: PlaneInk,
) -> Result<CentreEstimate, EstimateError> {
    let (p, steps) = match (seed, start) {
        (Some(s), super::Start::Track(_)) => (s.even_ink().p, Steps::FirstIfNear),
        (Some(s), _) => (s.even_ink().p, Steps::ToMinimum),
        (None, _) => (first_guess(g, k, paper, ink_level), Steps::ToMinimum),
    };
    let even = solve(prob, p, k, g, steps, None)?;
    let noise = even.residual_variance(prob).unwrap_or(1.0);
    let map =
        prior::refine(prob, &even.p, &ink, (noise, k)).ok_or_else(|| EstimateError::Diverged {
            iterations: 0,
            reason: "singular normal equations with the ink prior".into(),
        })?;
    if let Some(reason) = insane(&map.p, prob.np, k, g) {
        return Err(EstimateError::Diverged {
            iterations: 0,
            reason: format!("with the ink prior: {reason}"),
        });
    }
    let mut est = Fit { p: map.p, ..even }.estimate(prob);
    est.offset_cov_px2 = Some(map.offset_cov_px2);
    Ok(est)
}

/// The starting point from the guess alone: its centres and radii, a blur of 0.8 camera
/// pixels, the window's paper and ink levels.
fn first_guess(g: &Candidate, k: f64, paper: f64, ink: f64) -> [f64; MAXP] {
    let mut p = [0.0; MAXP];
    p[CXO] = g.outer_centre_px[0];
    p[CYO] = g.outer_centre_px[1];
    p[HOLE] = g.outer_radii_px[0];
    p[RIM] = g.outer_radii_px[1];
    p[CXI] = g.inner_centre_px[0];
    p[CYI] = g.inner_centre_px[1];
    p[RI] = g.inner_radii_px[1];
    p[RIH] = g.inner_radii_px[0];
    p[S] = 0.8 * k;
    p[B0] = paper;
    p[C] = 1.0 - ink / paper;
    p[CI] = p[C];
    p
}

/// The score (Lagrange multiplier) test of the contrast gradients at the even-ink minimum:
/// how much further a Gauss–Newton step with them free would lower the cost, in units of
/// the residual variance; χ² with 4 degrees of freedom when the ink is even.
fn uneven_ink_shows(even: &Problem, uneven: &Problem, fit: &Fit) -> bool {
    let Some(s2) = fit.residual_variance(even) else {
        return false;
    };
    let fresh;
    let at = match &fit.wide {
        Some(wide) => wide,
        None => {
            fresh = uneven.normal(&fit.p);
            &fresh
        }
    };
    let all: Vec<usize> = (0..uneven.np).collect();
    let held: Vec<usize> = all
        .iter()
        .copied()
        .filter(|i| !GRADIENTS.contains(i))
        .collect();
    match (gn_gain(at, &all), gn_gain(at, &held)) {
        (Some(full), Some(reduced)) => (full - reduced) / s2 > GRADIENTS_CHI2,
        _ => false,
    }
}

/// The cost a Gauss–Newton step in parameters `idx` would remove: `gᵀ H⁻¹ g`.
fn gn_gain(n: &Normal, idx: &[usize]) -> Option<f64> {
    let h = DMatrix::from_fn(idx.len(), idx.len(), |a, b| n.h[idx[a]][idx[b]]);
    let g = DVector::from_fn(idx.len(), |a, _| n.g[idx[a]]);
    h.cholesky().map(|c| g.dot(&c.solve(&g)))
}

/// The print's density inside the shapes of `state`, a converged fit of the target guessed
/// at `g` on `plane` (`k` its pixels per camera pixel), read where that fit read.
pub(super) fn density(
    plane: &Plane,
    win: &Window,
    g: &Candidate,
    k: f64,
    state: &State,
) -> Vec<DensitySample> {
    let prob = Problem {
        planes: state.planes,
        ..Problem::new(plane, win, g, sample_step(k), state.np)
    };
    density::read(&prob, &state.p)
}

/// A converged fit: the parameters and the normal equations there; and, when the fit's
/// last pass was made with the contrast gradients free too, those (for the score test).
struct Fit {
    p: [f64; MAXP],
    normal: Normal,
    wide: Option<Normal>,
}

impl Fit {
    fn residual_variance(&self, prob: &Problem) -> Option<f64> {
        let dof = self.normal.n.saturating_sub(prob.free());
        (dof > 0).then(|| self.normal.cost / dof as f64)
    }

    fn estimate(&self, prob: &Problem) -> CentreEstimate {
        let p = &self.p;
        let [so, si] = blur_shift::of_planes(prob, p);
        let offset_cov = prob
            .matrix(&self.normal)
            .try_inverse()
            .zip(self.residual_variance(prob))
            .map(|(inv, s2)| offset_block(&(inv * s2), [CXO, CYO], [CXI, CYI]));
        CentreEstimate {
            outer_px: [p[CXO] + so[0], p[CYO] + so[1]],
            inner_px: [p[CXI] + si[0], p[CYI] + si[1]],
            outer_radius_px: p[RIM],
            inner_radius_px: p[RI],
            offset_cov_px2: offset_cov,
            seed: Some(super::Seed(State {
                p: *p,
                np: prob.np,
                planes: prob.planes,
            })),
            even_ink: None,
        }
    }
}

/// The offset's (inner − outer centre) covariance from the parameters' covariance `c`,
/// the centres at rows `outer` and `inner` (x, y): `Cii + Coo − Cio − Coi` per pair of axes.
fn offset_block(c: &DMatrix<f64>, outer: [usize; 2], inner: [usize; 2]) -> [[f64; 2]; 2] {
    let e = |a: usize, b: usize| {
        let (ia, oa, ib, ob) = (inner[a], outer[a], inner[b], outer[b]);
        c[(ia, ib)] - c[(ia, ob)] - c[(oa, ib)] + c[(oa, ob)]
    };
    [[e(0, 0), e(0, 1)], [e(1, 0), e(1, 1)]]
}

/// Why parameters `q` are not a target (radii out of order, the blur or the centre out of
/// reach of the guess), if they are not.
fn insane(q: &[f64; MAXP], np: usize, k: f64, g: &Candidate) -> Option<String> {
    if q[..np].iter().any(|v| !v.is_finite()) {
        return Some("non-finite parameter".into());
    }
    if !(q[S] > 0.05 * k && q[S] < 0.5 * q[HOLE]) {
        return Some(format!("blur width {:.3} px out of range", q[S]));
    }
    if !(q[HOLE] > 0.0 && q[RIM] > q[HOLE] && q[RI] > 0.0) {
        return Some(format!(
            "radii out of order: hole {:.2}, rim {:.2}, inner {:.2}",
            q[HOLE], q[RIM], q[RI]
        ));
    }
    if np == MAXP && !(q[RIH] > 0.0 && q[RIH] < q[RI]) {
        return Some(format!(
            "inner ring radii out of order: {:.2}, {:.2}",
            q[RIH], q[RI]
        ));
    }
    let moved = (q[CXO] - g.outer_centre_px[0]).hypot(q[CYO] - g.outer_centre_px[1]);
    let limit = 3.0 * k + 0.25 * g.outer_radii_px[0];
    if moved > limit {
        return Some(format!("outer centre moved {moved:.2} px from the guess"));
    }
    None
}

/// How far [`solve`] iterates.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Steps {
    /// To the minimum (a short last step is taken without another pass).
    ToMinimum,
    /// A tracked target a frame later: the first Gauss–Newton step is the answer when it
    /// moves the centres by less than [`ONE_STEP_PX`]. From a start that close the step
    /// lands within ~1e-3 px of the minimum (Gauss–Newton's error is second order in the
    /// start's), a tenth of a frame's own noise, at half the passes.
    FirstIfNear,
}

/// The centre step below which a tracked fit's first step is its last, in camera pixels.
const ONE_STEP_PX: f64 = 0.1;

/// The cost a damped Gauss–Newton step `delta` is predicted to remove (the linearised
/// model's): `2·δᵀg − δᵀ(JᵀJ)δ`.
fn predicted_gain(h: &DMatrix<f64>, rhs: &DVector<f64>, delta: &DVector<f64>) -> f64 {
    2.0 * delta.dot(rhs) - delta.dot(&(h * delta))
}

/// A step this short (in the parameters' own σ², as `SHORT_STEP_SIGMAS2`) is likely the
/// last but one: the pass after it is made with the contrast gradients free too, so that
/// the score test can read that pass instead of making one more.
const WIDE_BELOW_SIGMAS2: f64 = 10.0;

/// Levenberg–Marquardt from `p` to the minimum. With `wide` (the same model with the
/// contrast gradients free), a pass that is likely the last is made with `wide` and kept
/// in the fit; the gradients still stay where they are (the sums of the other parameters
/// are the same bits either way).
fn solve(
    prob: &Problem,
    mut p: [f64; MAXP],
    k: f64,
    g: &Candidate,
    steps: Steps,
    wide: Option<&Problem>,
) -> Result<Fit, EstimateError> {
    let np = prob.np;
    let sane = |q: &[f64; MAXP]| insane(q, np, k, g);
    let diverged =
        |iterations: usize, reason: String| EstimateError::Diverged { iterations, reason };
    let mut cur = prob.normal(&p);
    let mut cur_wide = None;
    let mut lambda = 1e-3;
    let mut iterations = 0;
    let mut converged = false;
    while iterations < MAX_ITER {
        iterations += 1;
        let h = prob.matrix(&cur);
        let mut a = h.clone();
        for i in 0..np {
            a[(i, i)] += lambda * h[(i, i)].max(1e-12);
        }
        let rhs = DVector::from_fn(np, |i, _| cur.g[i]);
        let Some(delta) = a.cholesky().map(|c| c.solve(&rhs)) else {
            lambda *= 10.0;
            if lambda > 1e12 {
                return Err(diverged(iterations, "singular normal equations".into()));
            }
            continue;
        };
        let mut q = p;
        for i in 0..np {
            q[i] += delta[i];
        }
        let step_centres = [CXO, CYO, CXI, CYI]
            .iter()
            .map(|&i| delta[i].abs())
            .fold(0.0, f64::max);
        // The step's length in the parameters' own uncertainty (Mahalanobis distance²,
        // δᵀ(JᵀJ)δ/σ̂² ≈ the cost it removes over σ̂²): it counts every parameter, the
        // contrasts that move the edges too, where a length in pixels counts the geometry only.
        let sigma2 = cur.cost / cur.n.saturating_sub(prob.free()).max(1) as f64;
        let step_sigmas2 = (0..np).map(|i| delta[i] * rhs[i]).sum::<f64>() / sigma2.max(1e-300);
        let near = steps == Steps::FirstIfNear && iterations == 1 && step_centres < ONE_STEP_PX * k;
        if lambda <= 1e-2 && (near || step_sigmas2 < SHORT_STEP_SIGMAS2) && sane(&q).is_none() {
            // A Gauss–Newton step this short lands far within the noise of the minimum
            // (a tenth of a standard deviation away, and converging): take it without
            // paying for another pass (the curvature and residual variance for the
            // covariance change by far less than their own uncertainty).
            // The cost (for the residual variance) is the one the step is predicted to
            // leave.
            cur.cost = (cur.cost - predicted_gain(&h, &rhs, &delta)).max(0.0);
            p = q;
            converged = true;
            break;
        }
        if sane(&q).is_none() {
            let (next, next_wide) = match wide.filter(|_| step_sigmas2 < WIDE_BELOW_SIGMAS2) {
                Some(w) => {
                    let n = w.normal(&q);
                    (n.held(), Some(n))
                }
                None => (prob.normal(&q), None),
            };
            if next.cost <= cur.cost {
                let gain = cur.cost - next.cost;
                p = q;
                cur = next;
                cur_wide = next_wide;
                lambda = (lambda * 0.3).max(1e-9);
                // Converged: the centres move by less than 1e-4 px (0.08 µm at the
                // paper's scale, far below the noise) and the cost stops falling.
                if step_centres < 1e-4 * k && gain <= 1e-6 * cur.cost {
                    converged = true;
                    break;
                }
                continue;
            }
        }
        lambda *= 10.0;
        if lambda > 1e10 {
            // No step lowers the cost any more: at the minimum to working precision.
            converged = true;
            break;
        }
    }
    tracing::trace!(iterations, pixels = cur.n, converged, "fit");
    if let Some(reason) = sane(&p) {
        return Err(diverged(iterations, reason));
    }
    if !converged {
        return Err(diverged(
            iterations,
            format!("no convergence in {MAX_ITER} iterations"),
        ));
    }
    Ok(Fit {
        p,
        normal: cur,
        wide: cur_wide,
    })
}
