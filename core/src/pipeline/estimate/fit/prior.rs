//! The print's uneven ink as a prior: after the even-ink fit, the model
//! `I = L·(1 − (1 + ε)·(c_o·cov_o + c_i·cov_i))` with the ink's relative density ε a
//! Gaussian field of known RMS and correlation length, written in its Karhunen–Loève modes
//! over the target (unit prior variance each), fitted by maximum a posteriori: the
//! residuals' sum of squares over the data's variance plus the modes' squared norm.

use super::normal::Row;
use super::{offset_block, Problem, B0, BX, BY, CXI, CXO, CYI, CYO, GRADIENTS, MAXP};
use nalgebra::{DMatrix, DVector};
use std::sync::Arc;

/// The ink density's statistics ([`crate::pipeline::InkPrior`]) in a plane's pixels: with
/// `mean`, the density the calibration scan mapped on this target, and `density_rms` what
/// the map leaves unknown about it; without, a density of mean 0.
#[derive(Debug, Clone, PartialEq)]
pub struct PlaneInk {
    pub density_rms: f64,
    pub corr_px: f64,
    pub mean: Option<Arc<InkMean>>,
}

/// A density the prior is centred on: Gaussian bumps about the target's outer centre, in a
/// plane's pixels ([`crate::calibration::InkField`] learns them).
#[derive(Debug, Clone, PartialEq)]
pub struct InkMean {
    /// `[dx, dy, weight]` from the outer centre.
    pub bumps: Vec<[f64; 3]>,
    pub width_px: f64,
}

impl InkMean {
    /// The density at `d` from the outer centre, and its gradient.
    pub fn at(&self, d: [f64; 2]) -> (f64, [f64; 2]) {
        bumps_at(&self.bumps, self.width_px, d)
    }
}

/// The sum of Gaussian `bumps` (`[x, y, weight]`, each `width` wide) at `d`, and its
/// gradient.
pub fn bumps_at(bumps: &[[f64; 3]], width: f64, d: [f64; 2]) -> (f64, [f64; 2]) {
    let inv_w2 = 1.0 / (width * width);
    // Bumps beyond 6 widths add under 1e-8 of their weight.
    let reach2 = 36.0 * width * width;
    let (mut e, mut g) = (0.0, [0.0; 2]);
    for &[bx, by, w] in bumps {
        let (dx, dy) = (d[0] - bx, d[1] - by);
        let d2 = dx * dx + dy * dy;
        if d2 > reach2 {
            continue;
        }
        let v = w * (-0.5 * d2 * inv_w2).exp();
        e += v;
        g = [g[0] - v * dx * inv_w2, g[1] - v * dy * inv_w2];
    }
    (e, g)
}

/// Modes whose prior variance is at least this share of the largest's: the others move a
/// shape's edges by less than 10 % of what the largest do (their amplitude's RMS is under
/// a tenth), far below what the samples can tell.
const MODE_FLOOR: f64 = 1e-2;
const ITERATIONS: usize = 12;
/// At most this many samples per fit (see [`samples`]).
const MAX_SAMPLES: usize = 16_384;
/// The grid reaches at most this many steps from the target's centre (see [`modes`]).
const MAX_GRID_STEPS: i64 = 10;
/// What a fit with the prior holds at most: the samples' modes and their edges' moves, the
/// Jacobian and its transpose (f64), the grid at most `π·(MAX_GRID_STEPS + 1)²` points,
/// hence modes.
pub const PEAK_BYTES: u64 = {
    let modes = 3 * (MAX_GRID_STEPS as u64 + 1) * (MAX_GRID_STEPS as u64 + 1) + 1;
    8 * MAX_SAMPLES as u64 * (4 * modes + 2 * MAXP as u64)
};
/// Converged: no centre moved more than this, in the plane's sample steps.
const CONVERGED_STEPS: f64 = 1e-4;

/// The MAP fit: its parameters (the contrast gradients at 0: the modes hold the density)
/// and the offset's posterior covariance.
pub(super) struct Map {
    pub p: [f64; MAXP],
    pub offset_cov_px2: [[f64; 2]; 2],
}

/// The MAP fit from the even fit's `p`, `noise` its residual variance per sample, on a plane
/// `k` times finer than the camera's; `None` when the normal equations are singular.
///
/// On a reconstruction the fit reads 2 samples per camera pixel and axis, interpolated from
/// fewer camera pixels: the prior reads one per camera pixel (every `⌊k/step⌋`-th), each
/// counted `(k/(step·t))²` times (1 for an even k), at a quarter of the work and the same
/// information.
pub(super) fn refine(
    prob: &Problem,
    p: &[f64; MAXP],
    prior: &PlaneInk,
    (noise, k): (f64, f64),
) -> Option<Map> {
    let per_camera = ((k / prob.step as f64).floor() as usize).max(1);
    let samples = samples(prob, per_camera);
    let spacing = (prob.step * per_camera) as f64;
    let sigma2 = noise * (k / spacing).max(1.0).powi(2);
    // The lens blurs the inked density whole ([`super::blur_shift`]): each mode also moves
    // the edges, by s²·∇φ, through ∇K at the even fit's edges.
    let edge_weight: Vec<[f64; 2]> = samples
        .iter()
        .map(|smp| {
            let Row { j, l, .. } = prob.row_f64(p, smp.fx, smp.fy, smp.v);
            let s2 = p[super::S].powi(2) / l.max(1e-9);
            [s2 * (j[CXO] + j[CXI]), s2 * (j[CYO] + j[CYI])]
        })
        .collect();
    let known = known_density(p, prior.mean.as_deref(), &samples, &edge_weight);
    let post = Posterior {
        prob,
        phi: modes(p, prior, &samples, None),
        edge: modes(p, prior, &samples, Some(&edge_weight)),
        known,
        samples,
        sigma2,
        base: (0..prob.np).filter(|a| !GRADIENTS.contains(a)).collect(),
    };
    let (p, a) = post.maximum(*p, DVector::zeros(post.phi.ncols()))?;
    let cov = post.normal(&p, &a).0.cholesky()?.inverse();
    Some(Map {
        p,
        offset_cov_px2: post.offset_cov(&cov)?,
    })
}

/// The posterior over the base parameters (the contrast gradients held) and the modes'
/// amplitudes: the samples, each one's modes, the samples' variance.
struct Posterior<'a> {
    prob: &'a Problem<'a>,
    samples: Vec<Sample>,
    phi: DMatrix<f64>,
    /// Each sample's change per mode through the edges' blur, `s²·∇φ·∇K` (see
    /// [`modes`]).
    edge: DMatrix<f64>,
    /// Each sample's density and edges' move from the prior's mean ([`known_density`]).
    known: Vec<(f64, f64)>,
    sigma2: f64,
    base: Vec<usize>,
}

impl Posterior<'_> {
    /// The maximum a posteriori from (`p`, `a`), by damped Gauss–Newton steps.
    fn maximum(
        &self,
        mut p: [f64; MAXP],
        mut a: DVector<f64>,
    ) -> Option<([f64; MAXP], DVector<f64>)> {
        let (nb, m) = (self.base.len(), self.phi.ncols());
        let mut lambda = 1e-3;
        let mut cost = self.objective(&p, &a);
        for _ in 0..ITERATIONS {
            let (h, g) = self.normal(&p, &a);
            let mut damped = h.clone();
            for i in 0..nb + m {
                damped[(i, i)] += lambda * h[(i, i)].max(1e-12);
            }
            let delta = damped.cholesky()?.solve(&g);
            let mut q = p;
            for (i, &b) in self.base.iter().enumerate() {
                q[b] += delta[i];
            }
            let b = &a + delta.rows(nb, m);
            let next = self.objective(&q, &b);
            if next > cost {
                lambda *= 10.0;
                continue;
            }
            let centres = [CXO, CYO, CXI, CYI]
                .iter()
                .map(|&i| (q[i] - p[i]).abs())
                .fold(0.0, f64::max);
            (p, a, cost) = (q, b, next);
            lambda = (lambda * 0.3).max(1e-9);
            if centres < CONVERGED_STEPS * self.prob.step as f64 {
                break;
            }
        }
        Some((p, a))
    }

    /// `Σ r²/σ² + |a|²`.
    fn objective(&self, p: &[f64; MAXP], a: &DVector<f64>) -> f64 {
        let (eps, edge) = (&self.phi * a, &self.edge * a);
        let data: f64 = self
            .samples
            .iter()
            .enumerate()
            .map(|(i, s)| row(self.prob, p, s, self.density(i, &eps, &edge)).2.powi(2))
            .sum();
        data / self.sigma2 + a.norm_squared()
    }

    /// `JᵀJ/σ² + diag(0, I)` and `Jᵀr/σ² − (0, a)` (the Jacobian built whole, its products
    /// by the matrix library's blocked kernels).
    fn normal(&self, p: &[f64; MAXP], a: &DVector<f64>) -> (DMatrix<f64>, DVector<f64>) {
        let (nb, m) = (self.base.len(), self.phi.ncols());
        let (jac, r) = self.jacobian(p, a);
        // (`tr_mul` is a dot product per entry: the transpose's product is the blocked one.)
        let jt = jac.transpose();
        let mut h = &jt * &jac / self.sigma2;
        let mut g = &jt * &r / self.sigma2;
        for k in 0..m {
            h[(nb + k, nb + k)] += 1.0;
            g[nb + k] -= a[k];
        }
        (h, g)
    }

    /// The Jacobian (base parameters, then the modes) and the residuals.
    fn jacobian(&self, p: &[f64; MAXP], a: &DVector<f64>) -> (DMatrix<f64>, DVector<f64>) {
        let (s, phi, base) = (&self.samples, &self.phi, &self.base);
        let (nb, m) = (base.len(), phi.ncols());
        let (eps, edge) = (phi * a, &self.edge * a);
        let mut jac = DMatrix::<f64>::zeros(s.len(), nb + m);
        let (mut r, mut dk, mut dl) = (
            DVector::zeros(s.len()),
            DVector::zeros(s.len()),
            DVector::zeros(s.len()),
        );
        for (i, smp) in s.iter().enumerate() {
            let (j, d, res) = row(self.prob, p, smp, self.density(i, &eps, &edge));
            for (c, &b) in base.iter().enumerate() {
                jac[(i, c)] = j[b];
            }
            (dk[i], dl[i], r[i]) = (d[0], d[1], res);
        }
        // The modes' columns: each sample's ink change times the modes there, and the
        // edges' moves.
        for k in 0..m {
            let mut col = jac.column_mut(nb + k);
            col.zip_zip_apply(&phi.column(k), &dk, |o, f, d| *o = d * f);
            col.zip_zip_apply(&self.edge.column(k), &dl, |o, e, l| *o += l * e);
        }
        (jac, r)
    }

    /// Sample `i`'s density and edges' move: the mean's and the modes' (`eps`, `edge`).
    fn density(&self, i: usize, eps: &DVector<f64>, edge: &DVector<f64>) -> (f64, f64) {
        let (e0, m0) = self.known[i];
        (e0 + eps[i], m0 + edge[i])
    }

    /// The offset's covariance from the parameters' `cov` (indexed as `base`).
    fn offset_cov(&self, cov: &DMatrix<f64>) -> Option<[[f64; 2]; 2]> {
        let at = |i: usize| self.base.iter().position(|&b| b == i);
        Some(offset_block(
            cov,
            [at(CXO)?, at(CYO)?],
            [at(CXI)?, at(CYI)?],
        ))
    }
}

/// The pixels the fit reads (position from the window's middle, value) and where.
#[derive(Debug, Clone, Copy)]
pub(super) struct Sample {
    pub fx: f64,
    pub fy: f64,
    pub v: f64,
    pub at: [f64; 2],
}

/// The fit's samples, every `thin`-th of its lattice in x and y, `thin` the least that
/// keeps them within [`MAX_SAMPLES`] (a large target's window: memory and time stay
/// bounded; its samples then count as fewer, so the data weigh less against the prior).
pub(super) fn samples(prob: &Problem, min_thin: usize) -> Vec<Sample> {
    samples_at_most(prob, min_thin, MAX_SAMPLES)
}

/// [`samples`] with at most about `max` of them.
pub(super) fn samples_at_most(prob: &Problem, min_thin: usize, max: usize) -> Vec<Sample> {
    // The lattice's points in the reach's circle.
    let n = std::f64::consts::FRAC_PI_4 * (2.0 * prob.win.reach / prob.step as f64 + 1.0).powi(2);
    let thin = (n / max as f64).sqrt().ceil().max(min_thin as f64);
    let step = prob.step * thin as usize;
    let reach2 = prob.win.reach * prob.win.reach;
    let mut out = Vec::new();
    for y in (prob.win.y0..prob.win.y1).step_by(step) {
        for x in (prob.win.x0..prob.win.x1).step_by(step) {
            let (fx, fy) = (x as f64, y as f64);
            let (rx, ry) = (fx - prob.reach_centre[0], fy - prob.reach_centre[1]);
            if rx * rx + ry * ry > reach2 {
                continue;
            }
            out.push(Sample {
                fx: fx - prob.mid[0],
                fy: fy - prob.mid[1],
                v: prob.plane.data[y * prob.plane.width + x] as f64,
                at: [fx, fy],
            });
        }
    }
    out
}

/// Each sample's density from the prior's `mean` and its edges' move through the blur,
/// `w·∇ε` with `w` the sample's `edge_weight` (as [`modes`] makes the modes'); zeros
/// without a mean.
fn known_density(
    p: &[f64; MAXP],
    mean: Option<&InkMean>,
    s: &[Sample],
    edge_weight: &[[f64; 2]],
) -> Vec<(f64, f64)> {
    let Some(mean) = mean else {
        return vec![(0.0, 0.0); s.len()];
    };
    s.iter()
        .zip(edge_weight)
        .map(|(smp, w)| {
            let (e, g) = mean.at([smp.at[0] - p[CXO], smp.at[1] - p[CYO]]);
            (e, w[0] * g[0] + w[1] * g[1])
        })
        .collect()
}

/// Each sample's value of each mode (samples × modes): the field's Karhunen–Loève modes on
/// a grid `corr/2` apart over the outer shape (its rim and blur, and half a correlation
/// length beyond), extended between grid points by the covariance. With `along_gradient`,
/// each mode's derivative along the sample's vector instead, `w·∇φ`.
fn modes(
    p: &[f64; MAXP],
    prior: &PlaneInk,
    s: &[Sample],
    along_gradient: Option<&[[f64; 2]]>,
) -> DMatrix<f64> {
    let grid = Grid::of(p, prior);
    let (k, basis) = (grid.k, &grid.basis);
    let side = (2 * k + 1) as usize;
    let (mut ex, mut ey) = (vec![0.0; side], vec![0.0; side]);
    let inv_l2 = 1.0 / (prior.corr_px * prior.corr_px);
    let wt = basis.weights.transpose();
    let mut phi = DMatrix::<f64>::zeros(s.len(), basis.weights.ncols());
    // A block of samples at a time: grid points × samples, each sample's column contiguous.
    for (b, block) in s.chunks(BLOCK).enumerate() {
        let mut to_grid = DMatrix::<f64>::zeros(basis.grid.len(), block.len());
        for (i, (mut col, smp)) in to_grid.column_iter_mut().zip(block).enumerate() {
            grid.along(smp.at, &mut ex, &mut ey);
            for (v, &[gi, gj]) in col.iter_mut().zip(&basis.grid) {
                let c = grid.rms2 * ex[(gi + k) as usize] * ey[(gj + k) as usize];
                *v = match along_gradient {
                    None => c,
                    // w·∇ of the covariance: ∂ₓ exp(−d²/2ℓ²) = −(dₓ/ℓ²)·exp(−d²/2ℓ²).
                    Some(w) => {
                        let (dx, dy) = grid.to(smp.at, [gi, gj]);
                        let w = w[b * BLOCK + i];
                        -c * inv_l2 * (w[0] * dx + w[1] * dy)
                    }
                };
            }
        }
        // The weights are for unit RMS: the modes' variances scale with rms².
        let rows = (&wt * to_grid).transpose() / prior.density_rms;
        phi.rows_mut(b * BLOCK, block.len()).copy_from(&rows);
    }
    phi
}

/// The modes' grid about a fit's outer centre: corr/2 apart, at most `MAX_GRID_STEPS`
/// from the centre (a target many correlation lengths wide gets a coarser grid: fewer
/// modes than its print has, bounded work), reaching the rim, its blur and half a
/// correlation length beyond.
struct Grid {
    centre: [f64; 2],
    spacing: f64,
    k: i64,
    basis: std::sync::Arc<Basis>,
    rms2: f64,
    corr_px: f64,
}

impl Grid {
    fn of(p: &[f64; MAXP], prior: &PlaneInk) -> Grid {
        let reach = p[super::RIM] + 3.0 * p[super::S] + 0.5 * prior.corr_px;
        let spacing = (prior.corr_px / 2.0).max(reach / MAX_GRID_STEPS as f64);
        let k = ((reach / spacing).ceil() as i64).min(MAX_GRID_STEPS);
        Grid {
            centre: [p[CXO], p[CYO]],
            spacing,
            k,
            basis: Basis::of(k, spacing / prior.corr_px),
            rms2: prior.density_rms.powi(2),
            corr_px: prior.corr_px,
        }
    }

    /// The covariance's factors `exp(−d²/2ℓ²)` along x and y from `at` to each grid line
    /// (the covariance is separable).
    fn along(&self, at: [f64; 2], ex: &mut [f64], ey: &mut [f64]) {
        let l2 = 2.0 * self.corr_px * self.corr_px;
        for (t, (x, y)) in ex.iter_mut().zip(ey.iter_mut()).enumerate() {
            let (dx, dy) = self.to(at, [t as i64 - self.k; 2]);
            *x = (-dx * dx / l2).exp();
            *y = (-dy * dy / l2).exp();
        }
    }

    /// `at` less grid point (i, j).
    fn to(&self, at: [f64; 2], [i, j]: [i64; 2]) -> (f64, f64) {
        (
            at[0] - self.centre[0] - i as f64 * self.spacing,
            at[1] - self.centre[1] - j as f64 * self.spacing,
        )
    }
}

/// Samples whose covariances to the grid are held at once.
const BLOCK: usize = 1024;

/// The field's modes on the grid of points (i, j) with i² + j² ≤ k², `r·corr` apart, for a
/// unit RMS: the grid's covariance's eigenvectors over the square root of their variances,
/// those above [`MODE_FLOOR`]. It depends on k and r alone: made once per pair.
struct Basis {
    grid: Vec<[i64; 2]>,
    weights: DMatrix<f64>,
}

impl Basis {
    fn of(k: i64, r: f64) -> std::sync::Arc<Basis> {
        use std::collections::HashMap;
        use std::sync::{Arc, Mutex, OnceLock};
        type Made = Mutex<HashMap<(i64, u64), Arc<Basis>>>;
        static MADE: OnceLock<Made> = OnceLock::new();
        let made = MADE.get_or_init(Default::default);
        let key = (k, r.to_bits());
        if let Some(b) = made.lock().ok().and_then(|m| m.get(&key).cloned()) {
            return b;
        }
        let b = Arc::new(Basis::make(k, r));
        if let Ok(mut m) = made.lock() {
            m.insert(key, b.clone());
        }
        b
    }

    fn make(k: i64, r: f64) -> Basis {
        let grid: Vec<[i64; 2]> = (-k..=k)
            .flat_map(|i| (-k..=k).map(move |j| [i, j]))
            .filter(|&[i, j]| i * i + j * j <= k * k)
            .collect();
        // Points r·ℓ apart: d²/2ℓ² = (Δi² + Δj²)·r²/2.
        let kmat = DMatrix::from_fn(grid.len(), grid.len(), |a, b| {
            let d2 = (grid[a][0] - grid[b][0]).pow(2) + (grid[a][1] - grid[b][1]).pow(2);
            (-(d2 as f64) * r * r / 2.0).exp()
        });
        let eig = kmat.symmetric_eigen();
        let top = eig.eigenvalues.max();
        let keep: Vec<usize> = (0..grid.len())
            .filter(|&j| eig.eigenvalues[j] >= MODE_FLOOR * top)
            .collect();
        let weights = DMatrix::from_fn(grid.len(), keep.len(), |i, j| {
            eig.eigenvectors[(i, keep[j])] / eig.eigenvalues[keep[j]].sqrt()
        });
        Basis { grid, weights }
    }
}

/// The model's row at a sample with the density `eps` and its edges' move `edge`: base
/// parameters' derivatives, `[−L·K, −L]` (the density's and the edges' move's), residual.
fn row(
    prob: &Problem,
    p: &[f64; MAXP],
    s: &Sample,
    (eps, edge): (f64, f64),
) -> ([f64; MAXP], [f64; 2], f64) {
    let Row { j, l, shade } = prob.row_f64(p, s.fx, s.fy, s.v);
    let ink = 1.0 - shade;
    let shade_e = 1.0 - (1.0 + eps) * ink - edge;
    let mut out = j.map(|v| v * (1.0 + eps));
    let inv_half = prob.inv_half;
    out[B0] = shade_e;
    out[BX] = s.fx * inv_half * shade_e;
    out[BY] = s.fy * inv_half * shade_e;
    (out, [-l * ink, -l], s.v - l * shade_e)
}
