//! What the lens's blur of an uneven print does to the fit, and its correction.
//!
//! The fit's model multiplies the ink's contrast at a pixel by the blurred coverage,
//! `c(x)·C(x)`, C = G∗f. A lens (and the pixel's area, and a reconstruction's
//! interpolation) blur the inked density whole: `G∗(c·f) = c·C + s²·∇c·∇C + …` for a
//! Gaussian of variance s² (from `u·G(u) = −s²·∇G(u)`). The second term is C moved by
//! `s²·∇c/c`, an edge shift the model leaves out, of ~5 µm per edge point on the webcam's
//! print (4 % RMS over 3 mm, s ≈ 0.85 px).
//!
//! The prior's density modes carry the term in the fit's model itself (`prior`: each
//! mode's column is `−L·(K·φ + s²·∇φ·∇K)`). The contrast planes get it here, as a
//! correction: the fit answers a term it leaves out, m, by moving its parameters by
//! `Δ = (JᵀJ)⁻¹·Jᵀ·m`, part into the centres and part into the planes themselves (on a
//! disk about a fifth), and the correction takes that Δ from the centres it reports. It
//! does not change the fit's pixels, its residuals or its seed for the next frame.

use super::normal::Row;
use super::prior::samples_at_most;
use super::{Problem, C, CI, CXI, CXO, CYI, CYO, MAXP, S};
use nalgebra::{DMatrix, DVector};

/// At most about this many samples for the planes' response (a ratio of sums over the
/// window: the fit's own lattice, thinned on large windows, gives the same to ~1 %).
const MAX_SAMPLES: usize = 4096;

/// The left-out term at one sample, `−s²·(g_o·∇K_o + g_i·∇K_i)·L`, from the row's centre
/// derivatives (`∂I/∂x_o = L·c_o·∂cov_o/∂x`): `g` is each shape's relative contrast gradient
/// (px⁻¹), `∇c/c` for the planes, `∇ε` for the print's density.
fn left_out(j: &[f64; MAXP], s2: f64, g_o: [f64; 2], g_i: [f64; 2]) -> f64 {
    -s2 * (g_o[0] * j[CXO] + g_o[1] * j[CYO] + g_i[0] * j[CXI] + g_i[1] * j[CYI])
}

/// The centres' corrections `[outer, inner]` (px) for a fit with the contrast planes (none
/// without): the planes are linear, so each shape's `∇c/c` is its plane's gradient over its
/// level at the sample.
pub(super) fn of_planes(prob: &Problem, p: &[f64; MAXP]) -> [[f64; 2]; 2] {
    if !prob.planes {
        return [[0.0; 2]; 2];
    }
    let samples = samples_at_most(prob, 1, MAX_SAMPLES);
    let (s2, h) = (p[S] * p[S], prob.inv_half);
    let np = prob.np;
    let (mut jtj, mut jtm) = (DMatrix::<f64>::zeros(np, np), DVector::<f64>::zeros(np));
    for smp in &samples {
        let Row { j, .. } = prob.row_f64(p, smp.fx, smp.fy, smp.v);
        let (x, y) = (smp.fx * h, smp.fy * h);
        let rel = |c: usize| {
            let level = p[c] + p[c + 1] * x + p[c + 2] * y;
            if level <= 0.0 {
                return [0.0; 2];
            }
            [p[c + 1] * h / level, p[c + 2] * h / level]
        };
        let m = left_out(&j, s2, rel(C), rel(CI));
        let jv = DVector::from_column_slice(&j[..np]);
        jtj.ger(1.0, &jv, &jv, 1.0);
        jtm.axpy(m, &jv, 1.0);
    }
    // The fitted centres are the true ones moved by Δ: the correction is −Δ.
    match jtj.cholesky().map(|ch| ch.solve(&jtm)) {
        Some(d) => [[-d[CXO], -d[CYO]], [-d[CXI], -d[CYI]]],
        None => [[0.0; 2]; 2],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_left_out_term_is_the_edges_moved_by_s2_times_the_gradient() {
        // Moving a shape's centre by δ changes a pixel by j·δ: the term is that change for
        // δ = −s²·g per shape.
        let mut j = [0.0; MAXP];
        (j[CXO], j[CYO], j[CXI], j[CYI]) = (2.0, -1.0, 0.5, 3.0);
        let (g_o, g_i) = ([0.01, -0.02], [0.03, 0.0]);
        let want = -1.5 * (2.0 * 0.01 + 1.0 * 0.02 + 0.5 * 0.03);
        assert!((left_out(&j, 1.5, g_o, g_i) - want).abs() < 1e-15);
    }
}
