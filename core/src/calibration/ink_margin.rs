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
/// density; with twice its standard uncertainty added) is not read. TODO: measured.
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
