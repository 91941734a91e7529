//! Finding targets with no prior layout: a red outer ring around a red inner disk (or ring).
//!
//! 1. Ink mask: a pixel is ink when it is red, i.e. `(R - max(G, B)) / R` is above a
//!    threshold taken from the frame's own redness histogram ([`redness_threshold`]). The
//!    ratio does not depend on the illumination, so vignetting and uneven light do not move
//!    it; dark pixels (where the ratio is noise) are never ink.
//! 2. Connected components (8-connected) with their moments; pieces of a ring broken apart
//!    are put together when their combined moments make a round ring ([`merge_fragments`]).
//! 3. Shape: an outer ring is a component whose moments fit an annulus (area and mean
//!    squared radius give both radii), round (isotropic second moments, square bounding box
//!    of the annulus's size) with a hole where its centroid is. The inner shape is the
//!    largest component inside that hole, itself a round disk or annulus.
//! 4. Whatever looked like a target and cannot be measured is reported in `skipped` with the
//!    reason: red regions cut by the frame edge, rings too near the edge for their ROI, rings
//!    with nothing inside or grown into their disk, pieces that do not make a round ring,
//!    regions with a target's outline that are not a ring around a disk. Other red clutter
//!    (filled disks, rectangles, text) is rejected silently.

use super::plane::{Mix, Roi};
use super::Skipped;
use image::RgbImage;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DetectConfig {
    /// The highest redness threshold: a pixel is ink when `(R - max(G, B)) / R` is at least
    /// the frame's own threshold ([`redness_threshold`]), which never exceeds this.
    pub min_redness: f64,
    /// ... and its red value is at least this many DN (the ratio of dark pixels is noise).
    pub min_red_dn: u8,
    /// Smallest and largest rim radius of an outer ring, in pixels.
    pub min_outer_radius_px: f64,
    pub max_outer_radius_px: f64,
    /// Relative tolerance of the roundness checks (moments and bounding box).
    pub shape_tolerance: f64,
    /// Paper kept around the outer rim in a target's ROI, in pixels (room for the blur).
    pub roi_margin_px: f64,
}

impl Default for DetectConfig {
    fn default() -> Self {
        DetectConfig {
            min_redness: 0.4,
            min_red_dn: 20,
            min_outer_radius_px: 4.0,
            max_outer_radius_px: 250.0,
            shape_tolerance: 0.2,
            roi_margin_px: 4.0,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Candidate {
    pub outer_centre_px: [f64; 2],
    pub inner_centre_px: [f64; 2],
    /// [hole, rim] of the outer ring.
    pub outer_radii_px: [f64; 2],
    /// A disk: [0, r]; an inner ring: [hole, rim].
    pub inner_radii_px: [f64; 2],
    /// Box around the whole target with a margin for the blur.
    pub roi: Roi,
    /// The map (det 1) from image offsets about the target to offsets in which its printed
    /// circles are circles: a board off parallel and the lens image them as ellipses whose
    /// axes differ by up to ~3 % at a frame's corner. Known from a calibration's field
    /// model ([`crate::calibration::Calibration::rectify_at`]); `None` takes them round.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rectify: Option<[[f64; 2]; 2]>,
}

impl Candidate {
    /// The same target in coordinates shifted by `d` (e.g. `-roi origin` for a crop).
    pub fn translated(&self, d: [f64; 2]) -> Candidate {
        let mv = |p: [f64; 2]| [p[0] + d[0], p[1] + d[1]];
        Candidate {
            outer_centre_px: mv(self.outer_centre_px),
            inner_centre_px: mv(self.inner_centre_px),
            ..self.clone()
        }
    }

    /// The same target on a `k`-times finer grid whose pixel centres at integers keep the
    /// image convention: coarse x maps to fine `k·(x + ½) − ½`. The ROI is left as is.
    pub fn scaled(&self, k: f64) -> Candidate {
        let sc = |p: [f64; 2]| [k * (p[0] + 0.5) - 0.5, k * (p[1] + 0.5) - 0.5];
        Candidate {
            outer_centre_px: sc(self.outer_centre_px),
            inner_centre_px: sc(self.inner_centre_px),
            outer_radii_px: self.outer_radii_px.map(|r| r * k),
            inner_radii_px: self.inner_radii_px.map(|r| r * k),
            roi: self.roi,
            rectify: self.rectify,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Default)]
pub struct Detection {
    pub targets: Vec<Candidate>,
    pub skipped: Vec<Skipped>,
}

/// One connected ink region and its moments.
#[derive(Debug, Clone)]
struct Component {
    area: f64,
    centroid: [f64; 2],
    /// Central second moments per pixel: mean of dx², dy², dx·dy.
    mxx: f64,
    myy: f64,
    mxy: f64,
    bbox: [u32; 4], // x0, y0, x1, y1 inclusive
    touches_edge: bool,
    /// The labels (1-based) of the mask components it is made of: one, or the pieces of a
    /// ring broken apart that [`merge_fragments`] put together.
    pieces: Vec<u32>,
}

/// Shape of a component judged from its moments.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Form {
    /// Filled round disk of this radius.
    Disk(f64),
    /// Round annulus [hole, rim].
    Ring(f64, f64),
    Other,
}

impl Component {
    fn form(&self, tol: f64) -> Form {
        let m = self.mxx + self.myy; // mean r² about the centroid
        if self.area < 3.0 || m <= 0.0 {
            return Form::Other;
        }
        // Isotropy: an ellipse has m_xx != m_yy or m_xy != 0.
        let aniso = ((self.mxx - self.myy).powi(2) + 4.0 * self.mxy * self.mxy).sqrt() / m;
        if aniso > tol {
            return Form::Other;
        }
        let w = (self.bbox[2] - self.bbox[0] + 1) as f64;
        let h = (self.bbox[3] - self.bbox[1] + 1) as f64;
        if (w - h).abs() > tol * w.max(h) + 2.0 {
            return Form::Other;
        }
        // Annulus: area = π(Ro² - Ri²), mean r² = (Ro² + Ri²)/2.
        let half = self.area / (2.0 * PI);
        let ro2 = m + half;
        let ri2 = m - half;
        let ro = ro2.sqrt();
        // The bounding box of a round shape is its diameter (within a pixel or so).
        if (w + h) / 2.0 - 2.0 * ro > tol * 2.0 * ro + 2.5 || 2.0 * ro - (w + h) / 2.0 > 2.5 {
            return Form::Other;
        }
        if ri2 > (0.25 * ro).powi(2) {
            Form::Ring(ri2.sqrt(), ro)
        } else {
            // A filled disk has Ri² ≈ 0, but so has a square (Ri ≈ 0.2 Ro): demand the
            // area of the circle the bounding box holds (a square fills 4/π of it), with half
            // a pixel of slack around the circumference.
            let r_box = (w + h) / 4.0;
            let circle = PI * r_box * r_box;
            if (self.area - circle).abs() > 0.75 * tol * circle + 0.5 * PI * r_box {
                return Form::Other;
            }
            Form::Disk((self.area / PI).sqrt())
        }
    }
}

/// Redness in 1/256 of a pixel of red `r` and `m = max(G, B)`: `⌊256 (r − m) / r⌋`,
/// clamped to 0..=255, at `RED_LUT[r << 8 | m]` (0 for r = 0). One lookup per pixel: frame
/// 0's redness is read over every pixel on the critical path. 255 is exactly `m = 0` (the
/// unclamped 256), so a threshold of 256 is `q ≥ 255`.
static RED_LUT: [u8; 1 << 16] = {
    let mut t = [0u8; 1 << 16];
    let mut r = 1;
    while r < 256 {
        let mut m = 0;
        while m < r {
            let q = 256 * (r - m) / r;
            t[r << 8 | m] = if q > 255 { 255 } else { q as u8 };
            m += 1;
        }
        r += 1;
    }
    t
};

/// Each pixel's redness in 1/256 (`RED_LUT`), 0 where the pixel is too dark for the ratio to
/// mean anything (`R < min_red_dn`): what the ink mask and the threshold are both read from.
struct Redness {
    w: usize,
    h: usize,
    q: Vec<u8>,
}

impl Redness {
    /// The frame's redness and the histogram of its pixels bright enough to have one.
    fn of(img: &RgbImage, cfg: &DetectConfig) -> (Redness, [u64; 256]) {
        let (w, h) = (img.width() as usize, img.height() as usize);
        let min_r = cfg.min_red_dn;
        let mut q = vec![0u8; w * h];
        // Rows in parallel (frame 0's detection holds up every later frame), 16 at a time,
        // each chunk's histogram summed after.
        let rows = 16 * w.max(1);
        let hist = q
            .par_chunks_mut(rows)
            .zip(img.as_raw().par_chunks(rows * 3))
            .fold(
                || [0u64; 257],
                |mut hist, (q, px)| {
                    redness_rows(q, px, min_r, &mut hist);
                    hist
                },
            )
            .reduce(
                || [0u64; 257],
                |mut a, b| {
                    a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
                    a
                },
            );
        let mut bright = [0u64; 256];
        bright.copy_from_slice(&hist[..256]);
        (Redness { w, h, q }, bright)
    }

    /// The region `[x0, x1] × [y0, y1]` (inclusive) alone.
    fn crop(&self, [x0, y0, x1, y1]: [usize; 4]) -> Redness {
        let q = (y0..=y1)
            .flat_map(|y| &self.q[y * self.w + x0..=y * self.w + x1])
            .copied()
            .collect();
        Redness {
            w: x1 - x0 + 1,
            h: y1 - y0 + 1,
            q,
        }
    }
}

/// Redness of a run of pixels into `q`, counted in `hist` (bin 256: too dark). Four partial
/// histograms: runs of paper hit one bin, whose increments would otherwise wait on each
/// other.
fn redness_rows(q: &mut [u8], px: &[u8], min_r: u8, hist: &mut [u64; 257]) {
    let mut part = [[0u32; 257]; 4];
    for (j, (o, p)) in q.iter_mut().zip(px.chunks_exact(3)).enumerate() {
        let (r, m) = (p[0], p[1].max(p[2]));
        let v = RED_LUT[(r as usize) << 8 | m as usize];
        let dark = r < min_r;
        *o = if dark { 0 } else { v };
        part[j & 3][if dark { 256 } else { v as usize }] += 1;
    }
    for p in part {
        hist.iter_mut().zip(p).for_each(|(h, c)| *h += c as u64);
    }
}

/// The redness threshold (1/256) this frame's ink and paper call for: Otsu's split of the
/// redness histogram separates paper from ink; the threshold is halfway between the paper's
/// median and the ink's, i.e. the middle of a blurred edge, so a softer lens, a pinker
/// webcam colour or dim light do not thin the ring into pieces. Never above
/// `cfg.min_redness` (today's fixed threshold: a clean frame keeps it) and never within the
/// paper's noise (median + 8 MAD, at least 0.08).
pub fn redness_threshold(img: &RgbImage, cfg: &DetectConfig) -> f64 {
    redness_levels(&Redness::of(img, cfg).1, cfg).0
}

/// [`redness_threshold`] and the ink's median redness (the threshold when there is no ink),
/// from the histogram of the frame's redness.
fn redness_levels(hist: &[u64; 256], cfg: &DetectConfig) -> (f64, f64) {
    let ceiling = cfg.min_redness;
    let n: u64 = hist.iter().sum();
    if n == 0 {
        return (ceiling, ceiling);
    }
    let split = otsu(hist);
    let paper = median_in(hist, 0, split);
    let Some(paper) = paper else {
        return (ceiling, ceiling);
    };
    let mad = {
        let mut dev = [0u64; 256];
        for (q, &c) in hist[..split].iter().enumerate() {
            dev[(q as f64 - paper).abs().round().min(255.0) as usize] += c;
        }
        median_in(&dev, 0, 256).unwrap_or(0.0)
    };
    let floor = (paper + 8.0 * mad.max(0.5)).max(0.08 * 256.0);
    let ink = median_in(hist, split, 256);
    let thr = match ink {
        Some(ink) => (paper + ink) / 2.0,
        None => ceiling * 256.0,
    };
    let thr = (thr.max(floor) / 256.0).min(ceiling);
    (thr, ink.map_or(thr, |q| (q / 256.0).max(thr)))
}

/// Otsu's split of a histogram: the first bin of the upper class.
fn otsu(hist: &[u64; 256]) -> usize {
    let n: f64 = hist.iter().map(|&c| c as f64).sum();
    let total: f64 = hist
        .iter()
        .enumerate()
        .map(|(q, &c)| q as f64 * c as f64)
        .sum();
    let (mut w0, mut s0, mut best, mut split) = (0.0, 0.0, -1.0, 128);
    for (q, &c) in hist.iter().enumerate().take(255) {
        w0 += c as f64;
        s0 += q as f64 * c as f64;
        let w1 = n - w0;
        if w0 == 0.0 || w1 == 0.0 {
            continue;
        }
        let d = s0 / w0 - (total - s0) / w1;
        let between = w0 * w1 * d * d;
        if between > best {
            best = between;
            split = q + 1;
        }
    }
    split
}

/// Median bin of `hist[lo..hi]`, `None` when empty.
fn median_in(hist: &[u64; 256], lo: usize, hi: usize) -> Option<f64> {
    let n: u64 = hist[lo..hi].iter().sum();
    if n == 0 {
        return None;
    }
    let mut acc = 0;
    for (q, &c) in hist.iter().enumerate().take(hi).skip(lo) {
        acc += c;
        if 2 * acc >= n {
            return Some(q as f64);
        }
    }
    Some((hi - 1) as f64)
}

/// Ink mask, one byte per pixel (1 = ink), and whether each row has any ink: pixels at
/// least `threshold` red (see [`redness_threshold`]); dark pixels (redness 0) never are, as
/// thresholds are at least 0.08. No morphological closing: the gap between a ring and a
/// 5 mm-offset disk is ~2.6 px, which a 3x3 closing would bridge; a broken ring is put
/// together from its pieces instead ([`merge_fragments`]).
fn ink_mask(red: &Redness, threshold: f64) -> (Vec<u8>, Vec<bool>) {
    // `256 (r − m) ≥ t·r` is `⌊256 (r − m) / r⌋ ≥ t` for a whole t; 256 is `q = 255`.
    let thr = ((threshold * 256.0).round() as i32).clamp(1, 255) as u8;
    let mut mask = vec![0u8; red.w * red.h];
    if red.w == 0 {
        return (mask, vec![false; red.h]);
    }
    mask.par_chunks_mut(red.w)
        .zip(red.q.par_chunks(red.w))
        .with_min_len(16)
        .for_each(|(m, q)| {
            m.iter_mut()
                .zip(q)
                .for_each(|(m, &q)| *m = (q >= thr) as u8)
        });
    let rows = mask
        .chunks(red.w)
        .map(|r| r.iter().any(|&v| v != 0))
        .collect();
    (mask, rows)
}

/// 8-connected components of the mask; `labels` gets 1-based component indices (0 = paper).
fn components(
    mask: &[u8],
    rows: &[bool],
    w: usize,
    h: usize,
    labels: &mut Vec<u32>,
) -> Vec<Component> {
    if labels.capacity() < w * h {
        // Zeroed pages from the allocator: only the rows with ink are ever touched.
        *labels = vec![0; w * h];
    } else {
        labels.clear();
        labels.resize(w * h, 0);
    }
    let mut comps = Vec::new();
    let mut stack: Vec<(u32, u32)> = Vec::new();
    // Only rows with ink can start a component (most rows of a frame have none).
    let starts = (0..h).filter(|&y| rows[y]).flat_map(|y| y * w..(y + 1) * w);
    for start in starts {
        if mask[start] == 0 || labels[start] != 0 {
            continue;
        }
        let id = comps.len() as u32 + 1;
        let (mut n, mut sx, mut sy, mut sxx, mut syy, mut sxy) =
            (0f64, 0f64, 0f64, 0f64, 0f64, 0f64);
        let (sx0, sy0) = ((start % w) as f64, (start / w) as f64);
        let mut bbox = [u32::MAX, u32::MAX, 0, 0];
        labels[start] = id;
        stack.push(((start % w) as u32, (start / w) as u32));
        while let Some((x, y)) = stack.pop() {
            // Moments about the seed keep the sums small (no cancellation in f64).
            let (dx, dy) = (x as f64 - sx0, y as f64 - sy0);
            n += 1.0;
            sx += dx;
            sy += dy;
            sxx += dx * dx;
            syy += dy * dy;
            sxy += dx * dy;
            bbox[0] = bbox[0].min(x);
            bbox[1] = bbox[1].min(y);
            bbox[2] = bbox[2].max(x);
            bbox[3] = bbox[3].max(y);
            let (x, y) = (x as usize, y as usize);
            for ny in y.saturating_sub(1)..=(y + 1).min(h - 1) {
                for nx in x.saturating_sub(1)..=(x + 1).min(w - 1) {
                    let i = ny * w + nx;
                    if mask[i] != 0 && labels[i] == 0 {
                        labels[i] = id;
                        stack.push((nx as u32, ny as u32));
                    }
                }
            }
        }
        let (mx, my) = (sx / n, sy / n);
        comps.push(Component {
            area: n,
            centroid: [sx0 + mx, sy0 + my],
            mxx: sxx / n - mx * mx,
            myy: syy / n - my * my,
            mxy: sxy / n - mx * my,
            touches_edge: bbox[0] == 0
                || bbox[1] == 0
                || bbox[2] as usize == w - 1
                || bbox[3] as usize == h - 1,
            bbox,
            pieces: vec![id],
        });
    }
    comps
}

/// Components whose boxes lie within this many pixels of each other may be pieces of one
/// ring.
const FRAGMENT_GAP_PX: u32 = 4;

/// Pieces of a ring broken apart (blur, dim light, chroma subsampling, halos): components of
/// no round form whose boxes nearly touch are grouped; a group of two or more whose combined
/// moments make a round ring is appended as one component (its `pieces` the members). Groups
/// (or single components) with a target's outline that are not round come back as reasons to
/// skip them ([`looks_like_a_target`]): a target that failed a check is never dropped silently.
fn merge_fragments(
    comps: &mut Vec<Component>,
    tol: f64,
    cfg: &DetectConfig,
) -> Vec<(Skipped, [u32; 4])> {
    let loose: Vec<usize> = (0..comps.len())
        .filter(|&i| !comps[i].touches_edge && comps[i].area >= 3.0)
        .filter(|&i| comps[i].form(tol) == Form::Other)
        .collect();
    let mut parent: Vec<usize> = (0..loose.len()).collect();
    fn root(p: &mut [usize], mut i: usize) -> usize {
        while p[i] != i {
            p[i] = p[p[i]];
            i = p[i];
        }
        i
    }
    let near = |a: &Component, b: &Component| {
        let g = FRAGMENT_GAP_PX;
        a.bbox[0] <= b.bbox[2] + g
            && b.bbox[0] <= a.bbox[2] + g
            && a.bbox[1] <= b.bbox[3] + g
            && b.bbox[1] <= a.bbox[3] + g
    };
    for a in 0..loose.len() {
        for b in a + 1..loose.len() {
            if near(&comps[loose[a]], &comps[loose[b]]) {
                let (ra, rb) = (root(&mut parent, a), root(&mut parent, b));
                parent[ra] = rb;
            }
        }
    }
    let mut groups: std::collections::BTreeMap<usize, Vec<usize>> = Default::default();
    for (a, &i) in loose.iter().enumerate() {
        let r = root(&mut parent, a);
        groups.entry(r).or_default().push(i);
    }
    let mut skipped = Vec::new();
    for members in groups.into_values() {
        let merged = merged_component(comps, &members);
        match merged.form(tol) {
            Form::Ring(_, ro)
                if members.len() >= 2
                    && ro >= cfg.min_outer_radius_px
                    && ro <= cfg.max_outer_radius_px =>
            {
                comps.push(merged)
            }
            _ if looks_like_a_target(&merged, tol, cfg) => {
                let b = merged.bbox;
                let what = match members.len() {
                    1 => "red target-sized region that is not a ring around a disk (ring and inner disk touching, or a ring not closed)".to_string(),
                    n => format!("red ring split into {n} pieces that do not make a round ring"),
                };
                let reason = format!("{what} (box x {}..{}, y {}..{})", b[0], b[2], b[1], b[3]);
                let centre_px = [(b[0] + b[2]) as f64 / 2.0, (b[1] + b[3]) as f64 / 2.0];
                skipped.push((Skipped { centre_px, reason }, b))
            }
            _ => {}
        }
    }
    skipped
}

/// A region that is not round but has a target's outline: a square box of a ring's size,
/// mostly empty (a ring with its disk fills ~0.4 of its box; a filled square 1, a disk 0.79).
fn looks_like_a_target(c: &Component, tol: f64, cfg: &DetectConfig) -> bool {
    let (bw, bh) = (
        (c.bbox[2] - c.bbox[0] + 1) as f64,
        (c.bbox[3] - c.bbox[1] + 1) as f64,
    );
    let side = bw.max(bh);
    (bw - bh).abs() <= tol * side + 2.0
        && side >= 2.0 * cfg.min_outer_radius_px
        && side <= 2.0 * cfg.max_outer_radius_px + 2.0
        && c.area / (bw * bh) < 0.6
}

/// One component from several: their areas, centroids and second moments combined.
fn merged_component(comps: &[Component], members: &[usize]) -> Component {
    let n: f64 = members.iter().map(|&i| comps[i].area).sum();
    let mean = |k: usize| {
        members
            .iter()
            .map(|&i| comps[i].area * comps[i].centroid[k])
            .sum::<f64>()
            / n
    };
    let (cx, cy) = (mean(0), mean(1));
    let (mut mxx, mut myy, mut mxy) = (0.0, 0.0, 0.0);
    let mut bbox = [u32::MAX, u32::MAX, 0, 0];
    let mut pieces = Vec::new();
    for &i in members {
        let c = &comps[i];
        let (dx, dy) = (c.centroid[0] - cx, c.centroid[1] - cy);
        mxx += c.area * (c.mxx + dx * dx);
        myy += c.area * (c.myy + dy * dy);
        mxy += c.area * (c.mxy + dx * dy);
        bbox = [
            bbox[0].min(c.bbox[0]),
            bbox[1].min(c.bbox[1]),
            bbox[2].max(c.bbox[2]),
            bbox[3].max(c.bbox[3]),
        ];
        pieces.extend_from_slice(&c.pieces);
    }
    Component {
        area: n,
        centroid: [cx, cy],
        mxx: mxx / n,
        myy: myy / n,
        mxy: mxy / n,
        bbox,
        touches_edge: false,
        pieces,
    }
}

/// Find every target in a frame. A region that looked like a target but failed (a disk grown
/// into its ring, pieces that do not make a ring) is looked at again alone at higher
/// thresholds, between the frame's and the ink's redness, which thin the ink apart; a
/// target found so replaces its `skipped` entry.
pub fn detect(img: &RgbImage, cfg: &DetectConfig) -> Detection {
    let (red, hist) = Redness::of(img, cfg);
    let (threshold, ink) = redness_levels(&hist, cfg);
    let (mut det, retry) = detect_at(&red, cfg, threshold);
    let mut resolved = Vec::new();
    for (k, b) in retry {
        let m = cfg.roi_margin_px.ceil() as u32 + 2;
        let (x0, y0) = (b[0].saturating_sub(m), b[1].saturating_sub(m));
        let x1 = (b[2] + m).min(img.width() - 1);
        let y1 = (b[3] + m).min(img.height() - 1);
        let crop = red.crop([x0, y0, x1, y1].map(|v| v as usize));
        for frac in [0.35, 0.6] {
            let (d, _) = detect_at(&crop, cfg, threshold + frac * (ink - threshold));
            if let [t] = d.targets.as_slice() {
                let mut t = t.translated([x0 as f64, y0 as f64]);
                t.roi.x += x0;
                t.roi.y += y0;
                det.targets.push(t);
                resolved.push(k);
                break;
            }
        }
    }
    let mut k = 0;
    det.skipped.retain(|_| {
        k += 1;
        !resolved.contains(&(k - 1))
    });
    sort_reading_order(&mut det.targets);
    det
}

/// Rows of targets top to bottom, left to right within a row.
fn sort_reading_order(targets: &mut [Candidate]) {
    targets.sort_by(|a, b| {
        let (ya, yb) = (a.outer_centre_px[1], b.outer_centre_px[1]);
        if (ya - yb).abs() > a.outer_radii_px[1].min(b.outer_radii_px[1]) {
            ya.total_cmp(&yb)
        } else {
            a.outer_centre_px[0].total_cmp(&b.outer_centre_px[0])
        }
    });
}

/// [`detect`] at one redness threshold, with the `skipped` entries (index, box) worth a
/// second look.
fn detect_at(
    red: &Redness,
    cfg: &DetectConfig,
    threshold: f64,
) -> (Detection, Vec<(usize, [u32; 4])>) {
    let (w, h) = (red.w, red.h);
    let mut det = Detection::default();
    let mut retry = Vec::new();
    if w == 0 || h == 0 {
        return (det, retry);
    }
    let (mask, rows) = ink_mask(red, threshold);
    let mut labels = Vec::new();
    let mut comps = components(&mask, &rows, w, h, &mut labels);
    let tol = cfg.shape_tolerance;
    for (s, b) in merge_fragments(&mut comps, tol, cfg) {
        retry.push((det.skipped.len(), b));
        det.skipped.push(s);
    }
    let min_area = PI * cfg.min_outer_radius_px.powi(2) * 0.3;

    let forms: Vec<Form> = comps.iter().map(|c| c.form(tol)).collect();
    // Outer rings, largest first, so an inner ring is claimed by its outer one before it
    // could be taken for an outer ring itself.
    let mut rings: Vec<usize> = (0..comps.len())
        .filter(|&i| !comps[i].touches_edge)
        .filter(|&i| match forms[i] {
            Form::Ring(_, ro) => ro >= cfg.min_outer_radius_px && ro <= cfg.max_outer_radius_px,
            _ => false,
        })
        .collect();
    // The hole is paper (or another component) where the centroid is; a ring-shaped region
    // filled there is a ring grown into its disk: reported, not measured.
    rings.retain(|&i| {
        let c = comps[i].centroid;
        let (x, y) = (c[0].round() as usize, c[1].round() as usize);
        let hole = x < w && y < h && !comps[i].pieces.contains(&labels[y * w + x]);
        if !hole {
            retry.push((det.skipped.len(), comps[i].bbox));
            det.skipped.push(Skipped {
                centre_px: c,
                reason: "red ring-shaped region with ink at its centre: ring and inner disk touch (inner disk not found)".into(),
            });
        }
        hole
    });
    let ring_rim = |i: usize| match forms[i] {
        Form::Ring(_, ro) => ro,
        _ => 0.0,
    };
    rings.sort_by(|&a, &b| ring_rim(b).total_cmp(&ring_rim(a)));

    let mut used = vec![false; comps.len()];
    for &i in &rings {
        if used[i] {
            continue;
        }
        let Form::Ring(hole, rim) = forms[i] else {
            continue;
        };
        let c = &comps[i];
        // The inner shape: the largest round component inside the hole.
        let inner = (0..comps.len())
            .filter(|&j| j != i && !used[j] && comps[j].pieces.len() == 1)
            .filter(|&j| {
                let d = &comps[j];
                d.bbox[0] > c.bbox[0]
                    && d.bbox[1] > c.bbox[1]
                    && d.bbox[2] < c.bbox[2]
                    && d.bbox[3] < c.bbox[3]
            })
            .filter(|&j| {
                let reach = match forms[j] {
                    Form::Disk(r) => r,
                    Form::Ring(_, r) => r,
                    Form::Other => return false,
                };
                let d = &comps[j];
                let off = (d.centroid[0] - c.centroid[0]).hypot(d.centroid[1] - c.centroid[1]);
                off + reach <= hole + 1.5
            })
            .max_by(|&a, &b| comps[a].area.total_cmp(&comps[b].area));
        let centre = c.centroid;
        let Some(j) = inner else {
            let split = match c.pieces.len() {
                1 => String::new(),
                n => format!(", split into {n} pieces,"),
            };
            det.skipped.push(Skipped {
                centre_px: centre,
                reason: format!(
                    "red ring (rim radius {rim:.1} px){split} with no round inner disk or ring in its hole (inner disk not found)"
                ),
            });
            continue;
        };
        used[i] = true;
        used[j] = true;
        let inner_radii = match forms[j] {
            Form::Disk(r) => [0.0, r],
            Form::Ring(a, b) => [a, b],
            Form::Other => unreachable!("filtered above"),
        };
        let half = rim + cfg.roi_margin_px;
        let (x0, y0) = ((centre[0] - half).floor(), (centre[1] - half).floor());
        let (x1, y1) = ((centre[0] + half).ceil(), (centre[1] + half).ceil());
        if x0 < 0.0 || y0 < 0.0 || x1 > (w - 1) as f64 || y1 > (h - 1) as f64 {
            det.skipped.push(Skipped {
                centre_px: centre,
                reason: format!(
                    "target too close to the frame edge: its ROI ({:.0}..{:.0}, {:.0}..{:.0}) leaves the {w}x{h} frame",
                    x0, x1, y0, y1
                ),
            });
            continue;
        }
        det.targets.push(Candidate {
            outer_centre_px: centre,
            inner_centre_px: comps[j].centroid,
            outer_radii_px: [hole, rim],
            inner_radii_px: inner_radii,
            roi: Roi {
                x: x0 as u32,
                y: y0 as u32,
                w: (x1 - x0) as u32 + 1,
                h: (y1 - y0) as u32 + 1,
            },
            rectify: None,
        });
    }
    for (i, c) in comps.iter().enumerate() {
        if c.touches_edge && c.area >= min_area {
            det.skipped.push(Skipped {
                centre_px: c.centroid,
                reason: format!(
                    "red region of {:.0} px cut by the frame edge (box x {}..{}, y {}..{}): a cut target cannot be measured",
                    c.area, c.bbox[0], c.bbox[2], c.bbox[1], c.bbox[3]
                ),
            });
            used[i] = true;
        }
    }
    tracing::debug!(
        components = comps.len(),
        targets = det.targets.len(),
        skipped = det.skipped.len(),
        "detect"
    );
    (det, retry)
}

/// Mean of one channel over the pixels of `roi` whose distance from `c` lies in `[r0, r1]`.
fn ring_mean(img: &RgbImage, roi: Roi, c: [f64; 2], r0: f64, r1: f64) -> Option<[f64; 3]> {
    let mut s = [0.0; 3];
    let mut n = 0.0;
    let (r0sq, r1sq) = (r0 * r0.abs(), r1 * r1);
    for y in roi.y..(roi.y + roi.h).min(img.height()) {
        let dy = y as f64 - c[1];
        for x in roi.x..(roi.x + roi.w).min(img.width()) {
            let dx = x as f64 - c[0];
            let r2 = dx * dx + dy * dy;
            if r2 >= r0sq && r2 <= r1sq {
                let p = img.get_pixel(x, y).0;
                for k in 0..3 {
                    s[k] += p[k] as f64;
                }
                n += 1.0;
            }
        }
    }
    (n > 0.0).then(|| s.map(|v| v / n))
}

/// The channel (0=R, 1=G, 2=B) with the most ink-to-paper contrast over the found targets.
/// Green (the contrast of red ink on white paper) when there are no targets.
pub fn measurement_channel(img: &RgbImage, det: &Detection) -> usize {
    let contrast = ink_contrast(img, det).map_or([0.0, 1.0, 0.0], |c| c.map(f64::abs));
    (0..3)
        .max_by(|&a, &b| contrast[a].total_cmp(&contrast[b]))
        .unwrap_or(1)
}

/// The plane the targets are measured in: the channels weighted by the ink's contrast in
/// each ([`Mix::of_contrast`]); green alone when no target was found.
pub fn measurement_mix(img: &RgbImage, det: &Detection) -> Mix {
    ink_contrast(img, det).map_or(Mix::channel(1), Mix::of_contrast)
}

/// Paper minus ink per channel (DN), summed over the targets: the ink from the middle of
/// each ring's band (clear of the blurred edges when it is thick), the paper just outside
/// it. `None` without targets.
fn ink_contrast(img: &RgbImage, det: &Detection) -> Option<[f64; 3]> {
    if det.targets.is_empty() {
        return None;
    }
    let mut contrast = [0.0f64; 3];
    for t in &det.targets {
        let [hole, rim] = t.outer_radii_px;
        let c = t.outer_centre_px;
        let band = ((rim - hole) / 2.0 - 1.5).max(0.3);
        let mid = (rim + hole) / 2.0;
        let ink = ring_mean(img, t.roi, c, mid - band, mid + band);
        let paper = ring_mean(img, t.roi, c, rim + 2.0, f64::INFINITY);
        if let (Some(ink), Some(paper)) = (ink, paper) {
            for k in 0..3 {
                contrast[k] += paper[k] - ink[k];
            }
        }
    }
    Some(contrast)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cand() -> Candidate {
        Candidate {
            outer_centre_px: [10.0, 20.0],
            inner_centre_px: [11.0, 20.0],
            outer_radii_px: [16.0, 22.0],
            inner_radii_px: [0.0, 7.0],
            roi: Roi {
                x: 0,
                y: 0,
                w: 5,
                h: 5,
            },
            rectify: None,
        }
    }

    #[test]
    fn the_redness_table_and_mask_are_the_ratio_for_every_pixel() {
        // Every (R, max(G, B)) pair once: R down the rows, G across, B = 0.
        let img = RgbImage::from_fn(256, 256, |x, y| image::Rgb([y as u8, x as u8, 0]));
        let cfg = DetectConfig::default();
        let (red, hist) = Redness::of(&img, &cfg);
        let min_r = cfg.min_red_dn as i32;
        let mut want_hist = [0u64; 256];
        for (r, m) in (0..=255i32).flat_map(|r| (0..=255i32).map(move |m| (r, m))) {
            let q = (256 * (r - m) / r.max(1)).clamp(0, 255);
            let got = red.q[(r * 256 + m) as usize] as i32;
            assert_eq!(got, if r >= min_r { q } else { 0 }, "r {r}, max(g, b) {m}");
            if r >= min_r {
                want_hist[q as usize] += 1;
            }
        }
        assert_eq!(hist, want_hist);
        // The mask is the ratio's own test, `256 (R − m) ≥ t·R`, at every whole threshold
        // detection can ask for (0.08 .. 1.0), 256 included.
        for t in [20, 21, 64, 102, 200, 254, 255, 256] {
            let (mask, rows) = ink_mask(&red, t as f64 / 256.0);
            for (r, m) in (0..=255i32).flat_map(|r| (0..=255i32).map(move |m| (r, m))) {
                let want = r >= min_r && 256 * (r - m) >= t * r;
                assert_eq!(
                    mask[(r * 256 + m) as usize] == 1,
                    want,
                    "t {t}, r {r}, m {m}"
                );
            }
            assert!(rows[255]);
            assert!(!rows[0]);
        }
    }

    #[test]
    fn translated_and_scaled_keep_the_pixel_centre_convention() {
        let c = cand().translated([-4.0, 2.0]);
        assert_eq!(c.outer_centre_px, [6.0, 22.0]);
        assert_eq!(c.inner_centre_px, [7.0, 22.0]);
        // Pixel 0's centre on a 10x grid is fine pixel 4.5; its left edge stays at -0.5.
        let s = Candidate {
            outer_centre_px: [0.0, -0.5],
            ..cand()
        }
        .scaled(10.0);
        assert_eq!(s.outer_centre_px, [4.5, -0.5]);
        assert_eq!(s.outer_radii_px, [160.0, 220.0]);
        assert_eq!(s.inner_radii_px, [0.0, 70.0]);
    }

    /// Draw a binary shape and classify its one component.
    fn form_of(inside: impl Fn(f64, f64) -> bool) -> Form {
        let (w, h) = (80, 80);
        let mask: Vec<u8> = (0..w * h)
            .map(|i| inside((i % w) as f64 - 40.0, (i / w) as f64 - 40.0) as u8)
            .collect();
        let mut labels = Vec::new();
        let comps = components(&mask, &vec![true; h], w, h, &mut labels);
        assert_eq!(comps.len(), 1);
        comps[0].form(DetectConfig::default().shape_tolerance)
    }

    /// A 160x120 frame of paper with `ink` wherever `inside(x, y)` (about the centre).
    fn frame_of(ink: [u8; 3], inside: impl Fn(f64, f64) -> bool) -> RgbImage {
        RgbImage::from_fn(160, 120, |x, y| {
            let on = inside(x as f64 - 80.0, y as f64 - 60.0);
            image::Rgb(if on { ink } else { [230, 226, 218] })
        })
    }

    /// A ring (16..22 px) around a disk (7 px) offset by `off` px, cut by `cuts` radial gaps
    /// 3 px wide.
    fn target(off: f64, cuts: usize) -> impl Fn(f64, f64) -> bool {
        move |x: f64, y: f64| {
            let r = x.hypot(y);
            let gap = (0..cuts).any(|k| {
                let a = 2.0 * PI * k as f64 / cuts as f64 + 0.3;
                let along = x * a.cos() + y * a.sin();
                along > 0.0 && (x * a.sin() - y * a.cos()).abs() < 1.5
            });
            ((16.0..22.0).contains(&r) && !gap) || (x - off).hypot(y) < 7.0
        }
    }

    #[test]
    fn the_threshold_follows_the_ink_and_never_exceeds_the_fixed_one() {
        let cfg = DetectConfig::default();
        // Deep red ink (redness 0.73, paper 0.02): halfway, 0.37; redder ink is capped at 0.4.
        let red = frame_of([220, 60, 58], target(0.0, 0));
        let t = redness_threshold(&red, &cfg);
        assert!((t - 0.37).abs() < 0.01, "{t}");
        let deep = frame_of([220, 10, 10], target(0.0, 0));
        assert_eq!(redness_threshold(&deep, &cfg), cfg.min_redness);
        // Pink ink (redness 0.32, as a webcam's sRGB and crosstalk make it): halfway, ~0.16.
        let pink = frame_of([220, 150, 148], target(0.0, 0));
        let t = redness_threshold(&pink, &cfg);
        assert!((t - 0.16).abs() < 0.02, "{t}");
        assert_eq!(detect(&pink, &cfg).targets.len(), 1);
        // Paper only: the threshold stays above the paper's redness (nothing found).
        let blank = frame_of([0, 0, 0], |_, _| false);
        assert!(redness_threshold(&blank, &cfg) >= 0.08);
        assert!(detect(&blank, &cfg).skipped.is_empty());
    }

    #[test]
    fn a_ring_in_pieces_is_one_target_and_what_cannot_be_measured_is_said() {
        let cfg = DetectConfig::default();
        let ink = [220, 60, 58];
        let det = detect(&frame_of(ink, target(2.0, 3)), &cfg);
        assert_eq!(det.targets.len(), 1, "{:?}", det.skipped);
        let t = &det.targets[0];
        // The ring's pieces put back together: centre and rim as the whole ring's.
        assert!((t.outer_centre_px[0] - 80.0).abs() < 0.6, "{t:?}");
        assert!((t.outer_centre_px[1] - 60.0).abs() < 0.6, "{t:?}");
        assert!((t.outer_radii_px[1] - 22.0).abs() < 1.0, "{t:?}");
        assert!(det.skipped.is_empty(), "{:?}", det.skipped);
        // The same pieces with no disk: skipped, saying so.
        let det = detect(
            &frame_of(ink, |x, y| target(0.0, 3)(x, y) && x.hypot(y) > 10.0),
            &cfg,
        );
        assert!(det.targets.is_empty());
        assert_eq!(det.skipped.len(), 1, "{:?}", det.skipped);
        assert!(
            det.skipped[0].reason.contains("split into 3 pieces"),
            "{:?}",
            det.skipped
        );
        // A disk grown into its ring: one region, skipped, near the target's place.
        let det = detect(
            &frame_of(ink, |x, y| {
                target(10.0, 0)(x, y) || (y.abs() < 3.0 && x > 0.0 && x < 18.0)
            }),
            &cfg,
        );
        assert!(det.targets.is_empty());
        assert_eq!(det.skipped.len(), 1, "{:?}", det.skipped);
        let s = &det.skipped[0];
        assert!(
            (s.centre_px[0] - 80.0).hypot(s.centre_px[1] - 60.0) < 8.0,
            "{s:?}"
        );
    }

    #[test]
    fn moments_tell_rings_disks_and_clutter_apart() {
        let r = |x: f64, y: f64| x.hypot(y);
        match form_of(|x, y| r(x, y) >= 16.0 && r(x, y) < 22.0) {
            Form::Ring(hole, rim) => {
                assert!(
                    (hole - 16.0).abs() < 1.0 && (rim - 22.0).abs() < 1.0,
                    "{hole} {rim}"
                )
            }
            f => panic!("ring taken for {f:?}"),
        }
        match form_of(|x, y| r(x, y) < 8.0) {
            Form::Disk(rad) => assert!((rad - 8.0).abs() < 0.5, "{rad}"),
            f => panic!("disk taken for {f:?}"),
        }
        assert_eq!(form_of(|x, y| x.abs() < 25.0 && y.abs() < 4.0), Form::Other);
        assert_eq!(form_of(|x, y| x.abs() < 8.0 && y.abs() < 8.0), Form::Other);
        // An ellipse is not round.
        assert_eq!(
            form_of(|x, y| (x / 20.0).hypot(y / 12.0) < 1.0),
            Form::Other
        );
    }
}
