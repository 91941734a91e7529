//! Levenberg–Marquardt on a residual function, with the parameter covariance at the
//! minimum. Parameters are scaled by their typical sizes (µm positions, px/µm scales and
//! per-µm perspective differ by 14 orders), the Jacobian is by central differences.

use nalgebra::{DMatrix, DVector};

pub(crate) struct LmResult {
    pub p: Vec<f64>,
    /// `σ̂² (JᵀJ)⁻¹` in the parameters' own units, `σ̂² = SSR / (n − p)`.
    pub cov: DMatrix<f64>,
    pub residuals: Vec<f64>,
    /// The parameters' typical sizes (finite-difference steps).
    pub typ: Vec<f64>,
}

/// Minimise `Σ r(p)²` from `p0`; `typ` are the parameters' typical sizes (never 0).
/// `None` when the normal equations are singular at the minimum (a parameter the data do
/// not fix).
pub(crate) fn minimise(
    r: &dyn Fn(&[f64]) -> Vec<f64>,
    p0: &[f64],
    typ: &[f64],
) -> Option<LmResult> {
    let unscale =
        |z: &DVector<f64>| -> Vec<f64> { z.iter().zip(typ).map(|(z, t)| z * t).collect() };
    let rz = |z: &DVector<f64>| DVector::from_vec(r(&unscale(z)));
    let mut z = DVector::from_iterator(p0.len(), p0.iter().zip(typ).map(|(p, t)| p / t));
    let mut res = rz(&z);
    let mut cost = res.norm_squared();
    let mut lambda = 1e-3;
    for _ in 0..100 {
        let j = jacobian(&rz, &z, res.len());
        let jtj = j.transpose() * &j;
        let g = j.transpose() * &res;
        let mut improved = false;
        for _ in 0..12 {
            let mut a = jtj.clone();
            for i in 0..a.nrows() {
                a[(i, i)] += lambda * jtj[(i, i)].max(1e-12);
            }
            let Some(step) = a.cholesky().map(|c| c.solve(&(-&g))) else {
                lambda *= 10.0;
                continue;
            };
            let zn = &z + &step;
            let rn = rz(&zn);
            let cn = rn.norm_squared();
            if cn.is_finite() && cn <= cost {
                let rel = (cost - cn) / cost.max(1e-300);
                (z, res, cost) = (zn, rn, cn);
                lambda = (lambda / 10.0).max(1e-12);
                improved = rel > 1e-12 && step.norm() > 1e-12 * z.norm().max(1.0);
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    let j = jacobian(&rz, &z, res.len());
    let info = j.transpose() * &j;
    let inv = info.clone().cholesky()?.inverse();
    let dof = (res.len() as f64 - p0.len() as f64).max(1.0);
    let sigma2 = cost / dof;
    let mut cov = inv * sigma2;
    for i in 0..cov.nrows() {
        for k in 0..cov.ncols() {
            cov[(i, k)] *= typ[i] * typ[k];
        }
    }
    Some(LmResult {
        p: unscale(&z),
        cov,
        residuals: res.iter().copied().collect(),
        typ: typ.to_vec(),
    })
}

fn jacobian(
    rz: &dyn Fn(&DVector<f64>) -> DVector<f64>,
    z: &DVector<f64>,
    n: usize,
) -> DMatrix<f64> {
    let h = 1e-6;
    let mut j = DMatrix::zeros(n, z.len());
    for k in 0..z.len() {
        let (mut zp, mut zm) = (z.clone(), z.clone());
        zp[k] += h;
        zm[k] -= h;
        let d = (rz(&zp) - rz(&zm)) / (2.0 * h);
        j.set_column(k, &d);
    }
    j
}
