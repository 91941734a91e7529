//! How close to the shapes' edges the calibration's ink maps may read, chosen from the
//! scan's own cells.
//!
//! The fit's model of an edge is a blurred step. A camera that sharpens its frames, a lens
//! whose blur is not the model's, or JPEG's ringing leave halos just inside the edges that
//! the density's residuals read as ink. The closer the maps come to the edges, the less they
//! extrapolate to where the offsets are read — unless the halos come in with them. So the
//! samples are read from [`DENSITY_READ_MARGIN_S`] in, and each band of distance from the
//! edge is compared with the same shape's cells deeper in than [`DENSITY_EDGE_MARGIN_S`]:
//! the margin is the nearest band from which on every band reads the same ink as the
//! interior, within [`TOLERANCE`].
//!
//! [`DENSITY_READ_MARGIN_S`]: crate::pipeline::DENSITY_READ_MARGIN_S

use super::ink::{cells_read, InkMap};
use crate::pipeline::{DENSITY_EDGE_MARGIN_S, DENSITY_READ_MARGIN_S};
use serde::{Deserialize, Serialize};

/// The bands' width, in blur widths.
const BAND_S: f64 = 0.25;
/// A band whose mean density differs from the interior's by more than this (relative ink
/// density, with twice its standard uncertainty added) is not read. A third of what a
/// target's map leaves unknown at the edges (1.5–1.8 % RMS on the webcam): a bias that
/// size adds under 5 % to it in quadrature. On the webcam study's layout 11 the bands read
/// +0.61, +1.07, +1.33, +1.33 % (± 0.3) through the sharpened MJPEG camera (kept at 2.0)
/// and +0.14, +0.07, −0.01, +0.00 % (± 0.15) through the camera as config/rigd.toml
/// configures it (read from 1.0).
pub const TOLERANCE: f64 = 0.005;
/// Fewest cells of a shape on each side of a comparison.
const MIN_SHAPE_CELLS: usize = 3;

/// One band of distance inside the edges against the interior, over every shape scanned.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EdgeBand {
    /// Its distances inside the nearest edge, blur widths: `[from_s, to_s)`.
    pub from_s: f64,
    pub to_s: f64,
    /// Shapes with cells both in the band and in the interior.
    pub shapes: usize,
    /// The band's mean density less the interior's, averaged over those shapes, and its
    /// standard uncertainty (their scatter).
    pub density_diff: f64,
    pub u_density_diff: f64,
}

/// The margin chosen and the bands it was chosen from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InkMargin {
    /// How far inside the edges the maps read, blur widths.
    pub margin_s: f64,
    pub bands: Vec<EdgeBand>,
}

impl InkMargin {
    /// The margin the scan's `maps` allow (the default margin when they cannot say).
    pub fn choose(maps: &[InkMap]) -> InkMargin {
        let bands: Vec<EdgeBand> = band_edges()
            .filter_map(|(from_s, to_s)| EdgeBand::measure(maps, from_s, to_s))
            .collect();
        let mut margin_s = DENSITY_EDGE_MARGIN_S;
        // From the interior outwards: the margin moves out while the bands agree.
        for (from_s, to_s) in band_edges().rev() {
            let agrees = (bands.iter())
                .find(|b| b.from_s == from_s && b.to_s == to_s)
                .is_some_and(EdgeBand::agrees);
            if !agrees {
                break;
            }
            margin_s = from_s;
        }
        InkMargin { margin_s, bands }
    }

    /// Whether a band reads ink the interior does not, beyond its noise (3 standard
    /// uncertainties) and the tolerance: halos, most often a camera that sharpens its
    /// frames (the sharpened webcam's bands read 2.3–4.9 u out).
    pub fn halos(&self) -> bool {
        self.bands.iter().any(|b| {
            b.density_diff.abs() > TOLERANCE && b.density_diff.abs() > 3.0 * b.u_density_diff
        })
    }
}

/// The band a sample `edge_s` blur widths inside the edges falls in: its lower bound
/// ([`DENSITY_EDGE_MARGIN_S`] and deeper: the interior).
pub(super) fn band_from_s(edge_s: f64) -> f64 {
    if edge_s >= DENSITY_EDGE_MARGIN_S {
        return DENSITY_EDGE_MARGIN_S;
    }
    let i = ((edge_s - DENSITY_READ_MARGIN_S) / BAND_S).floor().max(0.0);
    DENSITY_READ_MARGIN_S + BAND_S * i
}

/// The bands from the read margin to the default one.
fn band_edges() -> impl DoubleEndedIterator<Item = (f64, f64)> {
    let n = ((DENSITY_EDGE_MARGIN_S - DENSITY_READ_MARGIN_S) / BAND_S).round() as usize;
    (0..n).map(|i| {
        let from = DENSITY_READ_MARGIN_S + BAND_S * i as f64;
        (from, from + BAND_S)
    })
}

impl EdgeBand {
    fn measure(maps: &[InkMap], from_s: f64, to_s: f64) -> Option<EdgeBand> {
        let diffs: Vec<f64> = (maps.iter())
            .flat_map(|m| [false, true].map(|inner| shape_diff(m, inner, from_s)))
            .flatten()
            .collect();
        let k = diffs.len();
        if k < 2 {
            return None;
        }
        let mean = diffs.iter().sum::<f64>() / k as f64;
        let var = diffs.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / (k - 1) as f64;
        Some(EdgeBand {
            from_s,
            to_s,
            shapes: k,
            density_diff: mean,
            u_density_diff: (var / k as f64).sqrt(),
        })
    }

    /// Whether the band reads the interior's ink, within the tolerance.
    fn agrees(&self) -> bool {
        self.density_diff.abs() + 2.0 * self.u_density_diff <= TOLERANCE
    }
}

/// One shape's mean density in the band from `from_s` less its interior's (`None`: too few cells).
fn shape_diff(map: &InkMap, inner: bool, from_s: f64) -> Option<f64> {
    let cells: Vec<_> = (cells_read(map, usize::MAX).into_iter())
        .filter(|c| c.inner == inner)
        .collect();
    let mean_of = |keep: &dyn Fn(f64) -> bool| {
        let means: Vec<f64> = (cells.iter())
            .filter(|c| keep(c.from_s))
            .map(|c| c.mean())
            .collect();
        (means.len() >= MIN_SHAPE_CELLS).then(|| means.iter().sum::<f64>() / means.len() as f64)
    };
    let band = mean_of(&|f| (f - from_s).abs() < 1e-9)?;
    let interior = mean_of(&|f| f >= DENSITY_EDGE_MARGIN_S)?;
    Some(band - interior)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::{DensitySample, InkShape};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, StandardNormal};

    /// 12 targets scanned over 21 frames: a disk of radius 8 px and a ring 12–20 px, blur
    /// 1 px; each sample reads white noise (2 %) plus `halo(edge_s)`, less its shape's mean.
    fn scanned(halo: impl Fn(f64) -> f64, seed: u64) -> Vec<InkMap> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let half = 0.5;
        (0..12)
            .map(|_| {
                let mut map = InkMap::default();
                for _ in 0..21 {
                    let jitter = [rng.gen::<f64>() - 0.5, rng.gen::<f64>() - 0.5];
                    let mut samples = Vec::new();
                    for (ix, iy) in (-20..=20).flat_map(|y| (-20..=20).map(move |x| (x, y))) {
                        let p = [ix as f64 + jitter[0], iy as f64 + jitter[1]];
                        let r = p[0].hypot(p[1]);
                        let (shape, edge) = match r {
                            r if r < 8.0 => (InkShape::Inner, 8.0 - r),
                            r if r > 12.0 && r < 20.0 => {
                                (InkShape::Outer, (r - 12.0).min(20.0 - r))
                            }
                            _ => continue,
                        };
                        let edge_s = edge - half;
                        if edge_s <= DENSITY_READ_MARGIN_S {
                            continue;
                        }
                        let noise: f64 = StandardNormal.sample(&mut rng);
                        samples.push(DensitySample {
                            from_centre_px: p,
                            shape,
                            density: halo(edge_s) + 0.02 * noise,
                            edge_s,
                        });
                    }
                    super::super::ink::remove_shape_means(&mut samples);
                    map.add(&samples, 1.0);
                }
                map
            })
            .collect()
    }

    #[test]
    fn samples_fall_in_quarter_blur_bands_and_the_interior() {
        assert_eq!(band_from_s(1.0), 1.0);
        assert_eq!(band_from_s(1.24), 1.0);
        assert_eq!(band_from_s(1.26), 1.25);
        assert_eq!(band_from_s(1.99), 1.75);
        assert_eq!(band_from_s(2.0), 2.0);
        assert_eq!(band_from_s(7.3), 2.0);
    }

    /// Without halos every band reads the interior's ink and the maps read from the read
    /// margin; a sharpened edge's halo (+1.5 % at 1 blur width, fading over 0.5) keeps
    /// them out to where it has faded under the tolerance.
    #[test]
    fn the_margin_comes_in_as_far_as_the_bands_read_the_interiors_ink() {
        for seed in 0..3 {
            let clean = InkMargin::choose(&scanned(|_| 0.0, seed));
            assert_eq!(clean.margin_s, DENSITY_READ_MARGIN_S, "{clean:?}");
            assert_eq!(clean.bands.len(), 4);
            for b in &clean.bands {
                assert!(
                    b.density_diff.abs() < 3.0 * b.u_density_diff + 1e-3,
                    "{b:?}"
                );
                assert_eq!(b.shapes, 24, "{b:?}");
            }
            let halo = |e: f64| 0.015 * (-(e - 1.0) / 0.5).exp();
            let haloed = InkMargin::choose(&scanned(halo, seed));
            // The bands read +1.1, +0.66, +0.37 (± 0.03), +0.2 % against the interior: the
            // third is the nearest within the tolerance with twice its uncertainty added.
            assert_eq!(haloed.margin_s, 1.5, "{haloed:?}");
            assert!(haloed.halos() && !clean.halos());
            let first = &haloed.bands[0];
            assert!(
                (first.density_diff - 0.011).abs() < 0.003,
                "the first band reads the halo: {first:?}"
            );
        }
    }

    /// A map read back from before the bands were kept has only interior cells: the
    /// margin stays the default and `within` keeps it whole.
    #[test]
    fn maps_without_bands_keep_the_default_margin() {
        let mut maps = scanned(|_| 0.0, 7);
        for m in &mut maps {
            m.cells.retain(|c| c.from_s == DENSITY_EDGE_MARGIN_S);
        }
        let mut old = toml::Value::try_from(&maps[0]).unwrap();
        for c in old["cells"].as_array_mut().unwrap() {
            c.as_table_mut().unwrap().remove("from_s").expect("kept");
        }
        let back: InkMap = old.try_into().unwrap();
        assert_eq!(back.cells, maps[0].cells);
        let m = InkMargin::choose(&maps);
        assert_eq!(m.margin_s, DENSITY_EDGE_MARGIN_S);
        assert!(m.bands.is_empty(), "{m:?}");
        assert_eq!(
            back.within(DENSITY_EDGE_MARGIN_S).cells.len(),
            back.cells.len()
        );
    }

    /// `within` merges a place's bands into one cell, from its nearest band kept.
    #[test]
    fn within_merges_a_places_bands() {
        let maps = scanned(|_| 0.0, 3);
        let m = &maps[0];
        let all: u32 = m.cells.iter().map(|c| c.n).sum();
        let merged = m.within(DENSITY_READ_MARGIN_S);
        assert_eq!(merged.cells.iter().map(|c| c.n).sum::<u32>(), all);
        let places: std::collections::HashSet<_> =
            m.cells.iter().map(|c| (c.inner, c.at)).collect();
        assert_eq!(merged.cells.len(), places.len());
        let deep = m.within(1.5);
        assert!(deep.cells.iter().all(|c| c.from_s >= 1.5));
        let kept: u32 = (m.cells.iter())
            .filter(|c| c.from_s >= 1.5)
            .map(|c| c.n)
            .sum();
        assert_eq!(deep.cells.iter().map(|c| c.n).sum::<u32>(), kept);
    }
}
