//! `combine = mean`: the per-frame offsets of one target averaged as they arrive, so no
//! frame's estimate is kept until the end.
//!
//! The mean is inverse-covariance weighted when every frame has a covariance (the fit) and
//! every one inverts: running sums of the information matrices and of the weighted offsets,
//! added in frame order, which is exactly what a batch over all frames sums. Otherwise it is
//! the plain mean (a running sum, as the batch) with the standard error of the scatter,
//! whose variance comes from Welford's update instead of a second pass over the offsets
//! (the two agree to rounding, ~1e-16 relative).

use super::estimate::CentreEstimate;
use nalgebra::{Matrix2, Vector2};

/// The running mean of one target's per-frame offsets.
#[derive(Debug, Clone)]
pub struct OffsetMean {
    n: usize,
    /// Every frame so far had a covariance, and each inverted.
    weighted: bool,
    info: Matrix2<f64>,
    info_offset: Vector2<f64>,
    sum: [f64; 2],
    /// Welford: the running mean and sum of squared deviations, per axis.
    mean: [f64; 2],
    m2: [f64; 2],
}

impl Default for OffsetMean {
    fn default() -> Self {
        OffsetMean {
            n: 0,
            weighted: true,
            info: Matrix2::zeros(),
            info_offset: Vector2::zeros(),
            sum: [0.0; 2],
            mean: [0.0; 2],
            m2: [0.0; 2],
        }
    }
}

impl OffsetMean {
    /// Frames averaged so far.
    pub fn frames(&self) -> usize {
        self.n
    }

    /// Add one frame's estimate.
    pub fn add(&mut self, e: &CentreEstimate) {
        let o = e.offset_px();
        self.n += 1;
        let inverse = e
            .offset_cov_px2
            .and_then(|c| Matrix2::new(c[0][0], c[0][1], c[1][0], c[1][1]).try_inverse());
        match (self.weighted, inverse) {
            (true, Some(w)) => {
                self.info += w;
                self.info_offset += w * Vector2::new(o[0], o[1]);
            }
            _ => self.weighted = false,
        }
        for (a, &x) in o.iter().enumerate() {
            self.sum[a] += x;
            let d = x - self.mean[a];
            self.mean[a] += d / self.n as f64;
            self.m2[a] += d * (x - self.mean[a]);
        }
    }

    /// The standard error of the plain mean from the offsets' scatter (`std / √n`), per
    /// axis; none below two frames.
    pub fn scatter_sigma(&self) -> Option<[f64; 2]> {
        let n = self.n;
        (n > 1).then(|| self.m2.map(|m2| (m2 / (n - 1) as f64 / n as f64).sqrt()))
    }

    /// (offset, its one-sigma uncertainty): weighted when every frame had an invertible
    /// covariance and their sum inverts, else plain with the standard error of the scatter
    /// (none from a single frame). NaN from no frame.
    pub fn result(&self) -> ([f64; 2], Option<[f64; 2]>) {
        let n = self.n;
        if n == 0 {
            return ([f64::NAN; 2], None);
        }
        if let (true, Some(cov)) = (self.weighted, self.info.try_inverse()) {
            let m = cov * self.info_offset;
            return (
                [m[0], m[1]],
                Some([cov[(0, 0)].max(0.0).sqrt(), cov[(1, 1)].max(0.0).sqrt()]),
            );
        }
        let mean = self.sum.map(|s| s / n as f64);
        let sigma = (n > 1).then(|| self.m2.map(|m2| (m2 / (n - 1) as f64 / n as f64).sqrt()));
        (mean, sigma)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn est(offset: [f64; 2], cov: Option<[[f64; 2]; 2]>) -> CentreEstimate {
        CentreEstimate {
            outer_px: [10.0, 20.0],
            inner_px: [10.0 + offset[0], 20.0 + offset[1]],
            outer_radius_px: 5.0,
            inner_radius_px: 2.0,
            offset_cov_px2: cov,
            seed: None,
            even_ink: None,
        }
    }

    #[test]
    fn plain_mean_and_standard_error_of_the_scatter() {
        let mut m = OffsetMean::default();
        for x in [0.1, 0.3, 0.2, 0.6] {
            m.add(&est([x, -x], None));
        }
        let (o, s) = m.result();
        // mean 0.3; sample std of {0.1, 0.3, 0.2, 0.6} = 0.21602, / sqrt(4) = 0.10801.
        assert!(
            (o[0] - 0.3).abs() < 1e-15 && (o[1] + 0.3).abs() < 1e-15,
            "{o:?}"
        );
        let s = s.unwrap();
        assert!(
            (s[0] - 0.108012).abs() < 1e-6 && (s[1] - s[0]).abs() < 1e-15,
            "{s:?}"
        );
    }

    #[test]
    fn covariances_weight_the_mean_until_one_frame_has_none() {
        let mut m = OffsetMean::default();
        // Variances 1 and 4 on x: weights 4/5 and 1/5, sigma sqrt(4/5).
        m.add(&est([1.0, 0.0], Some([[1.0, 0.0], [0.0, 1.0]])));
        m.add(&est([2.0, 0.0], Some([[4.0, 0.0], [0.0, 1.0]])));
        let (o, s) = m.result();
        assert!((o[0] - 1.2).abs() < 1e-12, "{o:?}");
        assert!((s.unwrap()[0] - 0.8f64.sqrt()).abs() < 1e-12);
        m.add(&est([3.0, 0.0], None));
        let (o, _) = m.result();
        assert!(
            (o[0] - 2.0).abs() < 1e-12,
            "plain mean once a frame has no covariance"
        );
        assert_eq!(m.frames(), 3);
        assert!(OffsetMean::default().result().0[0].is_nan());
    }
}
