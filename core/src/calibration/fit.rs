//! The fits: each target's own displacement per µm of travel (a straight line through its
//! centres), and the field model over all targets and steps (Levenberg–Marquardt).

use super::lm::{self, LmResult};
use super::model::FieldModel;
use super::scan::{CalibrationError, Scan};
use nalgebra::{DMatrix, Matrix2, Matrix3, Vector2, Vector3};

/// One target's straight-line fit `x = x0 + v·s + w·q` (s stage, q piezo travel).
#[derive(Debug, Clone)]
pub(crate) struct LineFit {
    pub x0_px: [f64; 2],
    /// px per µm of stage travel, and its covariance.
    pub v: Vector2<f64>,
    pub v_cov: Matrix2<f64>,
    /// px per µm of piezo travel (zero in a 1-D scan).
    pub w: Vector2<f64>,
    /// Per step (frame index, residual px).
    pub residuals_px: Vec<(usize, [f64; 2])>,
}

/// Fit one target's line; `None` with fewer than `min_steps` centres.
pub(crate) fn line_fit(scan: &Scan, t: usize, min_steps: usize, piezo: bool) -> Option<LineFit> {
    let obs: Vec<(usize, [f64; 2], [f64; 2])> = scan.targets[t]
        .centres_px
        .iter()
        .enumerate()
        .filter_map(|(i, c)| Some((i, scan.travel_um(i), (*c)?)))
        .collect();
    if obs.len() < min_steps {
        return None;
    }
    let cols = if piezo { 3 } else { 2 };
    let design = |tr: [f64; 2]| [1.0, tr[0], tr[1]];
    let mut xtx = Matrix3::zeros();
    let mut xty = [Vector3::zeros(), Vector3::zeros()];
    for (_, tr, c) in &obs {
        let d = Vector3::from(design(*tr));
        xtx += d * d.transpose();
        xty[0] += d * c[0];
        xty[1] += d * c[1];
    }
    if !piezo {
        xtx[(2, 2)] = 1.0; // the piezo column is all zero: keep the system invertible
    }
    let inv = xtx.try_inverse()?;
    let beta = [inv * xty[0], inv * xty[1]];
    let mut ssr = [0.0; 2];
    let residuals_px: Vec<(usize, [f64; 2])> = obs
        .iter()
        .map(|(i, tr, c)| {
            let d = Vector3::from(design(*tr));
            let r = [c[0] - beta[0].dot(&d), c[1] - beta[1].dot(&d)];
            ssr[0] += r[0] * r[0];
            ssr[1] += r[1] * r[1];
            (*i, r)
        })
        .collect();
    let dof = (obs.len() - cols).max(1) as f64;
    let var = Matrix2::new(ssr[0] / dof, 0.0, 0.0, ssr[1] / dof);
    Some(LineFit {
        x0_px: [beta[0][0], beta[1][0]],
        v: Vector2::new(beta[0][1], beta[1][1]),
        v_cov: var * inv[(1, 1)],
        w: Vector2::new(beta[0][2], beta[1][2]),
        residuals_px,
    })
}

/// How the board points are parameterised.
#[derive(Debug, Clone)]
pub(crate) enum Layout {
    /// No board: every target's place is free; the linear part is a scale (square pixels,
    /// the board's axes the image's at the centre: the gauge a 1-D scan leaves open).
    Free,
    /// The print's nominal centres (µm) of the fitted targets: `b = σ (P − o)`, the linear
    /// part general (the print fixes the shape, the stage the length).
    Board { nominal_um: Vec<[f64; 2]> },
}

/// The fit's parameters, in order: the field model's, the stage's direction (and the
/// piezo's), then the layout's (free: each target's place; board: `o`, `σ`).
pub(crate) struct FieldProblem<'a> {
    pub scan: &'a Scan,
    /// Scan target index of each fitted target.
    pub targets: Vec<usize>,
    pub layout: Layout,
    pub piezo: bool,
    pub base: FieldModel,
}

/// Indices into the parameter vector.
pub(crate) struct Ix {
    pub stage_dir: usize,
    pub piezo_dir: Option<usize>,
    /// The rail's zoom per µm of stage travel (board layout only): the rail out of the
    /// board's plane changes the board's distance, and the image zooms about its centre.
    pub zoom: Option<usize>,
    pub layout: usize,
}

impl FieldProblem<'_> {
    fn model_len(&self) -> usize {
        match self.layout {
            Layout::Free => 5,
            Layout::Board { .. } => 8,
        }
    }

    pub fn ix(&self) -> Ix {
        let m = self.model_len();
        let piezo_dir = self.piezo.then_some(m + 1);
        let after_dirs = m + 1 + self.piezo as usize;
        // With no board a 1-D scan cannot tell the zoom from the perspective (both make a
        // radial flow): it is not fitted, and `validation::gauge_rel_u` allows for it.
        let zoom = matches!(self.layout, Layout::Board { .. }).then_some(after_dirs);
        Ix {
            stage_dir: m,
            piezo_dir,
            zoom,
            layout: after_dirs + zoom.is_some() as usize,
        }
    }

    /// The rail's zoom per µm of stage travel in `p` (0 where it is not fitted).
    pub fn zoom(&self, p: &[f64]) -> f64 {
        self.ix().zoom.map_or(0.0, |k| p[k])
    }

    /// Image point of fitted target `j` in frame `i`: the model's, zoomed about the centre
    /// by the stage's travel.
    pub fn image(&self, p: &[f64], m: &FieldModel, j: usize, i: usize) -> [f64; 2] {
        let x = m.forward(self.point(p, j, i));
        let z = 1.0 - self.zoom(p) * self.scan.travel_um(i)[0];
        let c = m.centre_px;
        [c[0] + z * (x[0] - c[0]), c[1] + z * (x[1] - c[1])]
    }

    /// Image velocity (px per µm of stage travel) of the board point `b` after `s` µm of
    /// stage travel.
    pub fn velocity(&self, p: &[f64], b: [f64; 2], s: f64) -> Vector2<f64> {
        let m = self.model(p);
        let (d, _) = self.dirs(p);
        let at = [b[0] + s * d[0], b[1] + s * d[1]];
        let x = m.forward(at);
        let k = self.zoom(p);
        let flow = Vector2::new(x[0] - m.centre_px[0], x[1] - m.centre_px[1]);
        (1.0 - k * s) * (m.jacobian(at) * Vector2::new(d[0], d[1])) - k * flow
    }

    /// The field model of parameter vector `p`.
    pub fn model(&self, p: &[f64]) -> FieldModel {
        let q = match self.layout {
            Layout::Free => [p[0], 0.0, 0.0, p[0], p[1], p[2], p[3], p[4]],
            Layout::Board { .. } => std::array::from_fn(|i| p[i]),
        };
        self.base.with_params(&q)
    }

    /// Board point of fitted target `j` (its index in `targets`) with no travel.
    pub fn place(&self, p: &[f64], j: usize) -> [f64; 2] {
        let l = self.ix().layout;
        match &self.layout {
            Layout::Free => [p[l + 2 * j], p[l + 2 * j + 1]],
            Layout::Board { nominal_um } => {
                let (o, s) = ([p[l], p[l + 1]], p[l + 2]);
                [s * (nominal_um[j][0] - o[0]), s * (nominal_um[j][1] - o[1])]
            }
        }
    }

    /// Board displacement per µm of stage (and piezo) travel: unit vectors.
    pub fn dirs(&self, p: &[f64]) -> ([f64; 2], [f64; 2]) {
        let ix = self.ix();
        let unit = |a: f64| [a.cos(), a.sin()];
        let e = ix.piezo_dir.map_or([0.0; 2], |k| unit(p[k]));
        (unit(p[ix.stage_dir]), e)
    }

    /// Board point of fitted target `j` in frame `i`.
    pub fn point(&self, p: &[f64], j: usize, i: usize) -> [f64; 2] {
        let b = self.place(p, j);
        let (d, e) = self.dirs(p);
        let tr = self.scan.travel_um(i);
        [
            b[0] + tr[0] * d[0] + tr[1] * e[0],
            b[1] + tr[0] * d[1] + tr[1] * e[1],
        ]
    }

    /// Image minus model for every measured centre, px.
    pub fn residuals(&self, p: &[f64]) -> Vec<f64> {
        let m = self.model(p);
        let mut r = Vec::new();
        for (j, &t) in self.targets.iter().enumerate() {
            for (i, c) in self.scan.targets[t].centres_px.iter().enumerate() {
                let Some(c) = c else { continue };
                let x = self.image(p, &m, j, i);
                r.push(c[0] - x[0]);
                r.push(c[1] - x[1]);
            }
        }
        r
    }

    /// The starting point and the parameters' typical sizes.
    pub fn start(&self, lines: &[LineFit]) -> Result<(Vec<f64>, Vec<f64>), CalibrationError> {
        let s0 = self.base.a_px_per_um[0][0];
        // Perspective of a few degrees' tilt seen with f ~ the frame's half diagonal.
        let g_typ = s0 / self.base.norm_radius_px;
        let mean = |f: &dyn Fn(&LineFit) -> Vector2<f64>| {
            lines.iter().map(f).sum::<Vector2<f64>>() / lines.len() as f64
        };
        let (v, w) = (mean(&|l| l.v), mean(&|l| l.w));
        let angle = |u: Vector2<f64>| u[1].atan2(u[0]);
        let c = self.base.centre_px;
        let (mut p, mut typ) = (Vec::new(), Vec::new());
        match &self.layout {
            Layout::Free => {
                p.extend([s0, 0.0, 0.0, 0.0, 0.0]);
                typ.extend([s0, g_typ, g_typ, 0.01, 0.01]);
                p.push(angle(v));
                typ.push(1.0);
                if self.piezo {
                    p.push(angle(w));
                    typ.push(1.0);
                }
                for l in lines {
                    p.extend([(l.x0_px[0] - c[0]) / s0, (l.x0_px[1] - c[1]) / s0]);
                    typ.extend([1e5, 1e5]);
                }
            }
            Layout::Board { nominal_um } => {
                let (m, t) = affine(nominal_um, lines).ok_or_else(|| {
                    CalibrationError::Fit("the board's targets seen lie on one line".into())
                })?;
                let mi = m.try_inverse().expect("affine() returns an invertible map");
                let dv = mi * v;
                let sigma = 1.0 / dv.norm();
                let a = m / sigma;
                p.extend([
                    a[(0, 0)],
                    a[(0, 1)],
                    a[(1, 0)],
                    a[(1, 1)],
                    0.0,
                    0.0,
                    0.0,
                    0.0,
                ]);
                typ.extend([s0, s0, s0, s0, g_typ, g_typ, 0.01, 0.01]);
                p.push(angle(dv));
                typ.push(1.0);
                if self.piezo {
                    p.push(angle(mi * w));
                    typ.push(1.0);
                }
                // The zoom, per µm like the perspective and of its size.
                p.push(0.0);
                typ.push(g_typ);
                let o = mi * (Vector2::new(c[0], c[1]) - t);
                p.extend([o[0], o[1], sigma]);
                typ.extend([1e5, 1e5, 1.0]);
            }
        }
        Ok((p, typ))
    }

    pub fn solve(&self, lines: &[LineFit]) -> Result<LmResult, CalibrationError> {
        let (p0, typ) = self.start(lines)?;
        lm::minimise(&|p| self.residuals(p), &p0, &typ)
            .ok_or_else(|| CalibrationError::Fit("singular normal equations".into()))
    }

    /// d(model params)/d(fit params): constant (the model's parameters are a selection).
    pub fn model_selection(&self, np: usize) -> DMatrix<f64> {
        let mut t = DMatrix::zeros(8, np);
        match self.layout {
            Layout::Free => {
                t[(0, 0)] = 1.0;
                t[(3, 0)] = 1.0;
                for k in 1..5 {
                    t[(k + 3, k)] = 1.0;
                }
            }
            Layout::Board { .. } => {
                for k in 0..8 {
                    t[(k, k)] = 1.0;
                }
            }
        }
        t
    }
}

/// Least-squares affine map nominal (µm) -> frame-0 centre (px): `(M, t)`; `None` when
/// the points are collinear.
fn affine(nominal_um: &[[f64; 2]], lines: &[LineFit]) -> Option<(Matrix2<f64>, Vector2<f64>)> {
    let mut xtx = Matrix3::zeros();
    let mut xty = [Vector3::zeros(), Vector3::zeros()];
    for (n, l) in nominal_um.iter().zip(lines) {
        let d = Vector3::new(n[0], n[1], 1.0);
        xtx += d * d.transpose();
        xty[0] += d * l.x0_px[0];
        xty[1] += d * l.x0_px[1];
    }
    // Condition by the spread: collinear centres make the 3x3 system singular.
    let inv = xtx.try_inverse()?;
    let (bx, by) = (inv * xty[0], inv * xty[1]);
    let m = Matrix2::new(bx[0], bx[1], by[0], by[1]);
    (m.determinant().abs() > 1e-12 * m.norm_squared()).then_some((m, Vector2::new(bx[2], by[2])))
}
