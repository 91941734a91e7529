//! The print's ink density read off a converged fit: inside a shape, away from its blurred
//! edges, the model is `I = L·(1 − (1 + ε)·ink)`, so a pixel's residual `r` against the
//! fit says `ε = −r / (L·ink)` there. The fit's own contrasts have taken each shape's mean
//! of ε (its planes' slopes are put back); what is read is the rest, which is what a
//! calibration needs to learn the print's statistics and map it
//! ([`crate::calibration::ink`], [`crate::calibration::ink_field`]).

use super::prior::samples;
use super::{Problem, CXI, CXO, CYI, CYO, GRADIENTS, HOLE, MAXP, RI, RIH, RIM, S};

/// Which shape a density sample lies inside.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum InkShape {
    Outer,
    Inner,
}

/// The ink's relative density at one pixel inside a shape.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DensitySample {
    /// Where, from the fitted outer centre, px.
    pub from_centre_px: [f64; 2],
    pub shape: InkShape,
    pub density: f64,
}

/// How far inside a shape's edges a sample must lie, in blur widths (plus half a pixel):
/// the edge's model leaves ~2 % of its blur in the pixel there, and the readings the
/// webcam's sharpening halos reach still learn the print's statistics (4.27 % over 3037 µm,
/// the print's 4 % over 3000). At 2.5 s a softer, unsharpened edge (blur 0.88 px) left
/// the paper board's disks unread, and the rings' thin band alone read 2.9 % over 1423 µm;
/// at 2.0 s it reads 4.17 % over 3217 µm. At 1.5 s the sharpened webcam's halos read 12 %
/// high; at 3.0 s both lose shapes and read 2.7-3.4 % over 1.6-2.4 mm.
pub const EDGE_MARGIN_S: f64 = 2.0;

/// Every sample of the fit inside a shape, with the density the residual says there
/// against each shape's contrast at its centre: a fit with contrast planes has its planes
/// added back (they are the density's slope, which a map of the density needs).
pub(super) fn read(prob: &Problem, p: &[f64; MAXP]) -> Vec<DensitySample> {
    let mut flat = *p;
    for i in GRADIENTS {
        flat[i] = 0.0;
    }
    let margin = EDGE_MARGIN_S * p[S] + 0.5 * prob.step as f64;
    let inner_hole = if prob.np == MAXP {
        p[RIH]
    } else {
        f64::NEG_INFINITY
    };
    let inside = |rho: f64, lo: f64, hi: f64| rho > lo + margin && rho < hi - margin;
    samples(prob, 1)
        .into_iter()
        .filter_map(|s| {
            let (ox, oy) = (s.at[0] - p[CXO], s.at[1] - p[CYO]);
            let rho_o = prob.rho(ox, oy).0;
            let rho_i = prob.rho(s.at[0] - p[CXI], s.at[1] - p[CYI]).0;
            let shape = if inside(rho_o, p[HOLE], p[RIM]) {
                InkShape::Outer
            } else if inside(rho_i, inner_hole, p[RI]) {
                InkShape::Inner
            } else {
                return None;
            };
            let row = prob.row_f64(&flat, s.fx, s.fy, s.v);
            let ink = row.l * (1.0 - row.shade);
            (ink > 0.0).then(|| DensitySample {
                from_centre_px: [ox, oy],
                shape,
                density: (row.l * row.shade - s.v) / ink,
            })
        })
        .collect()
}
