//! A focus figure per target, for focusing and aligning by the numbers (the live view).
//!
//! `focus` is the target's gradient energy per unit of edge length over its contrast²:
//! Σ |∇I|² over the target's ROI (central differences) / ((paper − ink)² · L), with L the
//! length of the target's edges (the circles of its radii, from detection). For an edge
//! blurred by a Gaussian of σ px it is 1 / (2√π σ): it falls as the image defocuses and
//! does not change with the light (the contrast divides out). [`edge_sigma_px`] turns it
//! back into that σ (pixel area and the differences add about half a pixel to the lens's).

use super::detect::Candidate;
use super::plane::Plane;
use image::RgbImage;

/// The focus figure of target `c` in channel `channel` of `img` (1/px, higher is sharper);
/// `None` when its ROI has no contrast or no edges.
pub fn focus(img: &RgbImage, channel: usize, c: &Candidate) -> Option<f64> {
    let p = Plane::from_channel_roi(img, channel, c.roi);
    if p.width < 3 || p.height < 3 {
        return None;
    }
    let contrast = contrast(&p)?;
    let mut energy = 0.0f64;
    for y in 1..p.height - 1 {
        for x in 1..p.width - 1 {
            let gx = (p.at(x + 1, y) - p.at(x - 1, y)) as f64 / 2.0;
            let gy = (p.at(x, y + 1) - p.at(x, y - 1)) as f64 / 2.0;
            energy += gx * gx + gy * gy;
        }
    }
    let radii = c.outer_radii_px.iter().chain(&c.inner_radii_px);
    let edge_px: f64 = radii.map(|r| 2.0 * std::f64::consts::PI * r).sum();
    (edge_px > 0.0).then(|| energy / (contrast * contrast * edge_px))
}

/// The Gaussian edge blur σ (px) a focus figure means: 1 / (2√π · focus).
pub fn edge_sigma_px(focus: f64) -> f64 {
    1.0 / (2.0 * std::f64::consts::PI.sqrt() * focus)
}

/// Paper minus ink: the 90th minus the 10th percentile of the ROI (ink covers a good part
/// of a target's box, paper most of the rest).
fn contrast(p: &Plane) -> Option<f64> {
    let mut v: Vec<f32> = p.data.clone();
    let n = v.len();
    let lo = *v.select_nth_unstable_by(n / 10, f32::total_cmp).1 as f64;
    let hi = *v.select_nth_unstable_by(n * 9 / 10, f32::total_cmp).1 as f64;
    (hi - lo > 1.0).then_some(hi - lo)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::plane::Roi;

    /// A dark disk of radius `r` on white, its edge a Gaussian of `sigma` px (erf profile).
    fn disk(sigma: f64, r: f64) -> (RgbImage, Candidate) {
        let n = 64u32;
        let c = 31.5;
        let img = RgbImage::from_fn(n, n, |x, y| {
            let d = (x as f64 - c).hypot(y as f64 - c) - r;
            // 1/(1+exp(-1.702 d/σ)) is the normal CDF to within 1 %.
            let t = 1.0 / (1.0 + (-1.702 * d / sigma).exp());
            let v = (40.0 + 180.0 * t).round() as u8;
            image::Rgb([v, v, v])
        });
        let cand = Candidate {
            outer_centre_px: [c, c],
            inner_centre_px: [c, c],
            outer_radii_px: [0.0, r],
            inner_radii_px: [0.0, 0.0],
            roi: Roi {
                x: 4,
                y: 4,
                w: 56,
                h: 56,
            },
            rectify: None,
        };
        (img, cand)
    }

    #[test]
    fn focus_means_the_edge_blur_and_falls_with_it() {
        let mut last = f64::INFINITY;
        for sigma in [1.0, 1.5, 2.0, 3.0] {
            let (img, c) = disk(sigma, 16.0);
            let f = focus(&img, 1, &c).unwrap();
            assert!(f < last, "σ {sigma}: {f} not below {last}");
            last = f;
            // σ comes back within 15 % (the 8-bit rounding and the differences blur it).
            let s = edge_sigma_px(f);
            assert!((s - sigma).abs() < 0.15 * sigma, "σ {sigma} read as {s}");
        }
    }

    #[test]
    fn a_flat_roi_has_no_focus_figure() {
        let img = RgbImage::from_pixel(20, 20, image::Rgb([200, 200, 200]));
        let (_, mut c) = disk(1.0, 5.0);
        c.roi = Roi {
            x: 0,
            y: 0,
            w: 20,
            h: 20,
        };
        assert_eq!(focus(&img, 1, &c), None);
    }
}
