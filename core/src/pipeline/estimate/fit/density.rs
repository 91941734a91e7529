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
    /// How far inside its shape's nearest edge, in blur widths (less half a pixel): at least
    /// [`READ_MARGIN_S`]. The calibration keeps the samples from where the density reads
    /// the same as deeper inside (`calibration::ink_margin`).
    pub edge_s: f64,
}

/// The deepest margin the calibration's maps keep to, in blur widths inside a shape's
/// edges (plus half a pixel): where the bands cannot say, and the interior the bands are
/// compared with (`calibration::ink_margin`). The closer the readings come to the edges,
/// the less a target's map extrapolates to where the offsets are read, unless a
/// sharpening's halos come in with them. Layout 11 of the webcam study, 3 repeats, fixed
/// margins (the calibrated bias against the printed circles, 1 frame / 10 × 100 µm /
/// 20 × 50 µm, µm; the scan's statistics of the print's 4 % over 3000 µm):
///
/// | margin | webcam (MJPEG, sharpened) | the same as config/rigd.toml has it (YUYV, unsharpened) |
/// |---|---|---|
/// | 2.0 s | 12.4 / 6.8 / 6.9; 4.39 % over 2677 µm | 9.1 / 4.9 / 5.1; 4.05 % over 1727 µm |
/// | 1.5 s | 11.7 / 6.8 / 6.8; 4.31 % over 2868 µm | 8.0 / 4.8 / 4.9; 4.35 % over 2847 µm |
/// | 1.0 s | 10.6 / 6.7 / 6.0; 4.37 % over 3016 µm | 8.1 / 3.8 / 3.9; 4.68 % over 3058 µm |
///
/// Over the full study a fixed 1.0 s cut the bias on every layout through the camera as
/// configured but raised layout 13's through the sharpened MJPEG webcam (8.6 / 7.4 / 7.3
/// → 8.5 / 7.9 / 8.0 µm, 92 % within 2u): the halos the sharpening puts just inside the
/// edges enter its maps. The scan now tells the two apart by the bands' ink.
pub const EDGE_MARGIN_S: f64 = 2.0;

/// How far inside a shape's edges the fit reads samples, in blur widths (plus half a
/// pixel): the calibration then chooses, from the samples themselves, how close to the
/// edges its maps may come ([`EDGE_MARGIN_S`] at most). Tried at 0.5: through the camera
/// as config/rigd.toml configures it the bands still read the interior's ink there (0.50–
/// 0.75: +0.02 ± 0.14 %), and the suite's bias moved by 0.1–0.3 µm (against the print
/// 7.8 / 3.9 / 3.9 µm, at 1.0 8.1 / 3.8 / 3.9): not worth reading where the rough edges
/// and the edge model's misfit are largest.
pub const READ_MARGIN_S: f64 = 1.0;

/// Every sample of the fit inside a shape, with the density the residual says there
/// against each shape's contrast at its centre: a fit with contrast planes has its planes
/// added back (they are the density's slope, which a map of the density needs).
pub(super) fn read(prob: &Problem, p: &[f64; MAXP]) -> Vec<DensitySample> {
    let mut flat = *p;
    for i in GRADIENTS {
        flat[i] = 0.0;
    }
    let half_step = 0.5 * prob.step as f64;
    let inner_hole = if prob.np == MAXP {
        p[RIH]
    } else {
        f64::NEG_INFINITY
    };
    // Blur widths inside (lo, hi), less half a pixel; at least the read margin.
    let inside = |rho: f64, lo: f64, hi: f64| {
        let edge_s = ((rho - lo).min(hi - rho) - half_step) / p[S];
        (edge_s > READ_MARGIN_S).then_some(edge_s)
    };
    samples(prob, 1)
        .into_iter()
        .filter_map(|s| {
            let (ox, oy) = (s.at[0] - p[CXO], s.at[1] - p[CYO]);
            let rho_o = prob.rho(ox, oy).0;
            let rho_i = prob.rho(s.at[0] - p[CXI], s.at[1] - p[CYI]).0;
            let (shape, edge_s) = if let Some(e) = inside(rho_o, p[HOLE], p[RIM]) {
                (InkShape::Outer, e)
            } else if let Some(e) = inside(rho_i, inner_hole, p[RI]) {
                (InkShape::Inner, e)
            } else {
                return None;
            };
            let row = prob.row_f64(&flat, s.fx, s.fy, s.v);
            let ink = row.l * (1.0 - row.shade);
            (ink > 0.0).then(|| DensitySample {
                from_centre_px: [ox, oy],
                shape,
                density: (row.l * row.shade - s.v) / ink,
                edge_s,
            })
        })
        .collect()
}
