//! The paper's estimator: threshold the window halfway between the paper and ink levels,
//! split the ink pixels into the ring and the inner shape by their distance from the guessed
//! centres, and take each region's centroid. Every pixel counts fully or not at all, so the
//! result is quantised to the pixel grid: the faithful baseline, not a precise one.

use super::{CentreEstimate, EstimateError, Window};
use crate::pipeline::detect::Candidate;
use crate::pipeline::plane::Plane;
use std::f64::consts::PI;

/// Area and moments of a set of pixels.
#[derive(Default)]
struct Moments {
    n: f64,
    sx: f64,
    sy: f64,
    sxx: f64,
}

impl Moments {
    fn add(&mut self, x: f64, y: f64) {
        self.n += 1.0;
        self.sx += x;
        self.sy += y;
        self.sxx += x * x + y * y;
    }
    fn centroid(&self) -> [f64; 2] {
        [self.sx / self.n, self.sy / self.n]
    }
    /// Mean squared distance from the centroid.
    fn mean_r2(&self) -> f64 {
        let c = self.centroid();
        self.sxx / self.n - c[0] * c[0] - c[1] * c[1]
    }
    /// [hole, rim] of the annulus with this area and mean r²: area = π(Ro² − Ri²),
    /// mean r² = (Ro² + Ri²)/2. A disk has hole 0.
    fn annulus(&self) -> [f64; 2] {
        let m = self.mean_r2();
        let half = self.n / (2.0 * PI);
        [(m - half).max(0.0).sqrt(), (m + half).max(0.0).sqrt()]
    }
}

pub(super) fn estimate(
    plane: &Plane,
    win: &Window,
    g: &Candidate,
) -> Result<CentreEstimate, EstimateError> {
    let (paper, ink) = win.levels(plane, 1);
    let no_ink = |what: &str| EstimateError::NoInk {
        x: g.outer_centre_px[0],
        y: g.outer_centre_px[1],
        what: what.to_string(),
    };
    if paper - ink < 4.0 {
        return Err(no_ink(&format!(
            "no contrast between paper ({paper:.1} DN) and ink ({ink:.1} DN)"
        )));
    }
    let thr = 0.5 * (paper + ink) as f32;
    let [co, ci] = [g.outer_centre_px, g.inner_centre_px];
    let [hole, _] = g.outer_radii_px;
    let inner_rim = g.inner_radii_px[1];
    // Split the paper gap between the inner shape and the ring's hole in the middle.
    let reach_inner = (co[0] - ci[0]).hypot(co[1] - ci[1]) + inner_rim;
    let split = ((hole - reach_inner) / 2.0).max(0.0);
    // Distances compared squared: no square root per pixel (the fine grid has ~10⁵).
    let reach2 = win.reach * win.reach;
    let inner2 = (inner_rim + split) * (inner_rim + split);
    let ring_from = (hole - split).max(0.0);
    let ring2 = ring_from * ring_from;
    let (mut ring, mut inner) = (Moments::default(), Moments::default());
    for y in win.y0..win.y1 {
        let row = &plane.data[y * plane.width + win.x0..y * plane.width + win.x1];
        let fy = y as f64;
        for (x, &v) in (win.x0..win.x1).zip(row) {
            if v >= thr {
                continue;
            }
            let fx = x as f64;
            let ro2 = (fx - co[0]).powi(2) + (fy - co[1]).powi(2);
            if ro2 > reach2 {
                continue;
            }
            if (fx - ci[0]).powi(2) + (fy - ci[1]).powi(2) <= inner2 {
                inner.add(fx, fy);
            } else if ro2 >= ring2 {
                ring.add(fx, fy);
            }
        }
    }
    if ring.n < 3.0 {
        return Err(no_ink("no outer ring below the threshold"));
    }
    if inner.n < 1.0 {
        return Err(no_ink("no inner shape below the threshold"));
    }
    let inner_radius = if g.inner_radii_px[0] > 0.0 {
        inner.annulus()[1]
    } else {
        (inner.n / PI).sqrt()
    };
    Ok(CentreEstimate {
        outer_px: ring.centroid(),
        inner_px: inner.centroid(),
        outer_radius_px: ring.annulus()[1],
        inner_radius_px: inner_radius,
        offset_cov_px2: None,
        seed: None,
        even_ink: None,
    })
}
