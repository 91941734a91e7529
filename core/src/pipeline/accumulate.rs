//! Reconstruction that streams: each frame is added as it arrives and dropped, so memory
//! does not grow with the number of frames (docs/reconstruction.md, "Streaming").
//!
//! Both reconstructions ([`reconstruct::interp`], [`reconstruct::splat`]) are separable:
//! a row pass per frame (its x shift folded into the taps) whose output (H x kW) is summed
//! over the frames sharing a vertical fine shift, then one column pass per such group. The
//! row pass is done at [`Accumulator::add`] into the frame's group, so what is kept is one
//! H x kW sum per group, never a frame. Frames come in index order and each adds into its
//! group in that order, so the sums are the very ones a batch over all frames makes: the
//! result is bit for bit the batch's as long as no group had to be flushed.
//!
//! How many groups a run opens depends on its vertical shifts: per target (shifts of less
//! than half a pixel, the whole-pixel part moves the window) at most k + 2; a whole frame's
//! can be any number, so at most `max_open` are kept and the least recently used one is
//! flushed (its column pass added, unscaled, into the fine sum) when another is needed.
//!
//! [`reconstruct::interp`]: super::reconstruct::interp
//! [`reconstruct::splat`]: super::reconstruct::splat

use super::reconstruct::{tap_table, Fine, Taps, View};
use rayon::prelude::*;
use std::collections::BTreeMap;

/// Which reconstruction an [`Accumulator`] builds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// Cubic upsample, shift, average (the paper's).
    Interp,
    /// Direct shift-and-add.
    Splat,
}

/// Frames sharing one vertical fine shift: their row passes summed.
struct Group {
    /// `h x k w`: the sum of the group's row passes.
    rows: Vec<f32>,
    /// Splat: how many of the group's frames reach each fine column (empty for interp).
    count_x: Vec<f32>,
    last_used: u64,
    /// Whether a frame was added: the first one writes its row pass, later ones add. (A
    /// first `+=` reads the zeroed pages first, and each page is then faulted twice, the
    /// second time with a TLB shootdown across the cores: ~8 ms of a 20-frame job.)
    written: bool,
}

/// Column passes of groups flushed before the end, not yet divided by anything.
struct Flushed {
    /// The fine-grid sum (interp: without the 1/N; splat: without the division by counts).
    sum: Vec<f32>,
    /// Splat: how many camera pixels landed on each fine pixel (empty for interp).
    weight: Vec<f32>,
}

/// The fine pixels a reconstruction is read at: every `step`-th column from `phase[0]` and
/// every `step`-th row from `phase[1]` ([`super::estimate::lattice_read`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Lattice {
    pub step: usize,
    pub phase: [usize; 2],
}

impl Lattice {
    /// Every pixel.
    const ALL: Lattice = Lattice {
        step: 1,
        phase: [0, 0],
    };
}

/// A reconstruction being built, one frame at a time.
pub struct Accumulator {
    method: Method,
    width: usize,
    height: usize,
    k: usize,
    max_open: usize,
    groups: BTreeMap<i64, Group>,
    flushed: Option<Flushed>,
    frames: usize,
    tick: u64,
    /// Splat: frame 0, for the fine pixels no frame reaches.
    first: Vec<f32>,
    /// Interp: the fine pixels computed; the others are left 0.
    lattice: Lattice,
}

impl Accumulator {
    /// An empty reconstruction of `width x height` frames on the `k`-times finer grid,
    /// keeping at most `max_open` (at least 1) groups' sums before flushing one.
    pub fn new(method: Method, width: usize, height: usize, k: usize, max_open: usize) -> Self {
        assert!(k >= 1, "k >= 1");
        assert!(width >= 1 && height >= 1, "a frame of at least one pixel");
        Accumulator {
            method,
            width,
            height,
            k,
            max_open: max_open.max(1),
            groups: BTreeMap::new(),
            flushed: None,
            frames: 0,
            tick: 0,
            first: Vec::new(),
            lattice: Lattice::ALL,
        }
    }

    /// Compute only the fine pixels on `lattice` (interp; a splat computes every pixel): the
    /// reconstruction of a target that only the fit reads and nobody looks at, at a fifth
    /// of the row passes' cost and a 25th of the column pass's for k = 10. The pixels on the
    /// lattice are bit for bit those of the whole reconstruction. Set before the first frame.
    pub fn only_at(mut self, lattice: Lattice) -> Self {
        assert_eq!(self.frames, 0, "the lattice is set before the first frame");
        self.lattice = lattice;
        self
    }

    /// Frames added so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Groups whose sums are held now.
    pub fn open_groups(&self) -> usize {
        self.groups.len()
    }

    /// Whether a group had to be flushed (the result is then the batch's to f32 rounding).
    pub fn flushed(&self) -> bool {
        self.flushed.is_some()
    }

    /// Add a frame shifted by `shift` fine pixels ([`super::reconstruct::fine_shift`]).
    ///
    /// # Panics
    /// If the frame's size is not the accumulator's (a programming error).
    pub fn add(&mut self, frame: View, shift: [i64; 2]) {
        let (w, h, k) = (self.width, self.height, self.k);
        assert!(frame.width == w && frame.height == h, "frames of one size");
        if self.frames == 0 && self.method == Method::Splat {
            self.first = frame.data.to_vec();
        }
        self.frames += 1;
        self.tick += 1;
        if !self.groups.contains_key(&shift[1]) && self.groups.len() >= self.max_open {
            self.flush_oldest();
        }
        let fw = w * k;
        let method = self.method;
        let g = self.groups.entry(shift[1]).or_insert_with(|| Group {
            rows: vec![0.0; h * fw],
            count_x: match method {
                Method::Splat => vec![0.0; fw],
                Method::Interp => Vec::new(),
            },
            last_used: 0,
            written: false,
        });
        g.last_used = self.tick;
        match method {
            Method::Interp => interp_rows(g, frame, shift[0], k, &self.lattice),
            Method::Splat => splat_rows(g, frame, shift[0], k),
        }
    }

    /// Column-pass the least recently used group into the flushed sum.
    fn flush_oldest(&mut self) {
        let Some((&sy, _)) = self.groups.iter().min_by_key(|(_, g)| g.last_used) else {
            return;
        };
        let g = self.groups.remove(&sy).expect("the group just found");
        let n = self.width * self.k * self.height * self.k;
        let f = self.flushed.get_or_insert_with(|| Flushed {
            sum: vec![0.0; n],
            weight: match self.method {
                Method::Splat => vec![0.0; n],
                Method::Interp => Vec::new(),
            },
        });
        match self.method {
            Method::Interp => {
                let cols = (&g.rows[..], sy, &self.lattice);
                interp_cols(&mut f.sum, cols, self.height, self.k, 1.0, true)
            }
            Method::Splat => {
                splat_cols(&mut f.sum, &g.rows, sy, self.height, self.k);
                splat_weight(&mut f.weight, &g.count_x, sy, self.height * self.k);
            }
        }
    }

    /// The reconstruction of every frame added.
    ///
    /// # Panics
    /// If no frame was added.
    pub fn finish(self) -> Fine {
        self.finish_in(Vec::new())
    }

    /// [`Accumulator::finish`] into `buf`'s memory when it is large enough (zeroed first):
    /// a caller finishing many reconstructions in turn hands each one's buffer to the next,
    /// and their pages are faulted in once, not once each.
    ///
    /// # Panics
    /// If no frame was added.
    pub fn finish_in(mut self, buf: Vec<f32>) -> Fine {
        assert!(self.frames > 0, "at least one frame");
        let (fw, fh) = (self.width * self.k, self.height * self.k);
        let buf = zeroed(buf, fw * fh);
        let data = match self.method {
            Method::Interp => self.finish_interp(buf),
            Method::Splat => self.finish_splat(buf),
        };
        Fine {
            width: fw,
            height: fh,
            k: self.k,
            data,
        }
    }

    /// The column pass of every open group with the 1/N of the average folded into the
    /// weights; the first group writes, later ones add (no zero-fill or scaling pass).
    fn finish_interp(&mut self, zeros: Vec<f32>) -> Vec<f32> {
        let (h, k) = (self.height, self.k);
        let inv = 1.0 / self.frames as f32;
        let (mut out, mut first_group) = match self.flushed.take() {
            Some(mut f) => {
                f.sum.par_iter_mut().for_each(|v| *v *= inv);
                (f.sum, false)
            }
            None => (zeros, true),
        };
        for (&sy, g) in &self.groups {
            let cols = (&g.rows[..], sy, &self.lattice);
            interp_cols(&mut out, cols, h, k, inv, !first_group);
            first_group = false;
        }
        out
    }

    /// Sum the open groups' column passes, divide each fine pixel by how many camera pixels
    /// landed on it; a fine pixel none reached (only at the border) takes frame 0's value.
    fn finish_splat(&mut self, zeros: Vec<f32>) -> Vec<f32> {
        let (w, h, k) = (self.width, self.height, self.k);
        let (fw, fh) = (w * k, h * k);
        let (mut out, flushed_weight) = match self.flushed.take() {
            Some(f) => (f.sum, Some(f.weight)),
            None => (zeros, None),
        };
        for (&sy, g) in &self.groups {
            splat_cols(&mut out, &g.rows, sy, h, k);
        }
        let reach: Vec<(&Vec<f32>, Vec<bool>)> = self
            .groups
            .iter()
            .map(|(&sy, g)| {
                let ry = (0..fh as i64).map(|y| (0..fh as i64).contains(&(y + sy)));
                (&g.count_x, ry.collect())
            })
            .collect();
        let first = View::new(&self.first, w, h);
        out.par_chunks_mut(fw)
            .with_min_len(rows_per_task(fw))
            .enumerate()
            .for_each(|(yy, dst)| {
                for (xx, d) in dst.iter_mut().enumerate() {
                    let open: f32 = reach
                        .iter()
                        .filter(|(_, ry)| ry[yy])
                        .map(|(cx, _)| cx[xx])
                        .sum();
                    let n = flushed_weight.as_ref().map_or(0.0, |wt| wt[yy * fw + xx]) + open;
                    *d = if n > 0.0 {
                        *d / n
                    } else {
                        first.at(xx / k, yy / k)
                    };
                }
            });
        out
    }
}

/// Rows of `width` values one parallel task takes at least: a target's window (~35 000
/// values) is one task, since splitting work that small across threads costs more than it
/// gains; a whole frame's rows are shared out.
fn rows_per_task(width: usize) -> usize {
    (MIN_TASK_VALUES / width.max(1)).max(1)
}

/// Values below which a pass over rows is not split across threads.
const MIN_TASK_VALUES: usize = 1 << 16;

/// `n` zeros in `buf`'s memory if it has room, else freshly allocated (zero pages the
/// system maps on first touch).
fn zeroed(mut buf: Vec<f32>, n: usize) -> Vec<f32> {
    if buf.capacity() < n {
        return vec![0.0; n];
    }
    buf.clear();
    buf.resize(n, 0.0);
    buf
}

/// Interp's row pass of one frame into its group: resampled along x, written by the
/// group's first frame and added by the others (on the lattice's columns only).
fn interp_rows(g: &mut Group, frame: View, sx: i64, k: usize, lattice: &Lattice) {
    let w = frame.width;
    let fw = w * k;
    let table = tap_table(w, k, sx);
    let add = std::mem::replace(&mut g.written, true);
    let (px, step) = (lattice.phase[0], lattice.step);
    g.rows
        .par_chunks_mut(fw)
        .with_min_len(rows_per_task(fw))
        .enumerate()
        .for_each(|(y, acc)| {
            let src = &frame.data[y * w..(y + 1) * w];
            let tap = |t: &Taps| {
                t.w[0] * src[t.idx[0] as usize]
                    + t.w[1] * src[t.idx[1] as usize]
                    + t.w[2] * src[t.idx[2] as usize]
                    + t.w[3] * src[t.idx[3] as usize]
            };
            let cols = acc.iter_mut().zip(&table);
            match (step, add) {
                (1, true) => cols.for_each(|(a, t)| *a += tap(t)),
                (1, false) => cols.for_each(|(a, t)| *a = tap(t)),
                (_, true) => cols.skip(px).step_by(step).for_each(|(a, t)| *a += tap(t)),
                (_, false) => cols.skip(px).step_by(step).for_each(|(a, t)| *a = tap(t)),
            }
        });
}

/// Interp's column pass of a group's sum (`rows`, its vertical shift `sy`, the lattice)
/// into `out`, weights scaled by `scale`: written, or added when `add`. Off the lattice,
/// `out` is not touched.
fn interp_cols(
    out: &mut [f32],
    (rows, sy, lattice): (&[f32], i64, &Lattice),
    h: usize,
    k: usize,
    scale: f32,
    add: bool,
) {
    let fw = rows.len() / h;
    let col: Vec<Taps> = tap_table(h, k, sy)
        .into_iter()
        .map(|t| Taps {
            idx: t.idx,
            w: t.w.map(|w| w * scale),
        })
        .collect();
    let (step, px) = (lattice.step, lattice.phase[0]);
    let on_lattice = |&(yy, _): &(usize, &mut [f32])| yy % step == lattice.phase[1] % step;
    out.par_chunks_mut(fw)
        .with_min_len(rows_per_task(fw) * step)
        .enumerate()
        .filter(on_lattice)
        .for_each(|(yy, dst)| {
            let t = col[yy];
            let r: [&[f32]; 4] = std::array::from_fn(|j| &rows[t.idx[j] as usize * fw..][..fw]);
            let w = t.w;
            let taps = dst.iter_mut().zip(r[0]).zip(r[1]).zip(r[2]).zip(r[3]);
            let v = |a: &f32, b: &f32, c: &f32, d: &f32| w[0] * a + w[1] * b + w[2] * c + w[3] * d;
            match (step, add) {
                // The whole grid: plain loops, which vectorise.
                (1, true) => taps.for_each(|((((o, a), b), c), d)| *o += v(a, b, c, d)),
                (1, false) => taps.for_each(|((((o, a), b), c), d)| *o = v(a, b, c, d)),
                (_, true) => taps
                    .skip(px)
                    .step_by(step)
                    .for_each(|((((o, a), b), c), d)| *o += v(a, b, c, d)),
                (_, false) => taps
                    .skip(px)
                    .step_by(step)
                    .for_each(|((((o, a), b), c), d)| *o = v(a, b, c, d)),
            }
        });
}

/// Splat's row pass of one frame into its group: fine column X takes camera column
/// floor((X + sx) / k), if inside.
fn splat_rows(g: &mut Group, frame: View, sx: i64, k: usize) {
    let w = frame.width;
    let fw = (w * k) as i64;
    let src_x: Vec<Option<u32>> = (0..fw)
        .map(|x| {
            let f = x + sx;
            (0..fw).contains(&f).then(|| (f / k as i64) as u32)
        })
        .collect();
    for (c, s) in g.count_x.iter_mut().zip(&src_x) {
        *c += s.is_some() as u8 as f32;
    }
    g.rows
        .par_chunks_mut(fw as usize)
        .with_min_len(rows_per_task(fw as usize))
        .enumerate()
        .for_each(|(y, acc)| {
            let src = &frame.data[y * w..(y + 1) * w];
            for (a, s) in acc.iter_mut().zip(&src_x) {
                if let Some(x) = s {
                    *a += src[*x as usize];
                }
            }
        });
}

/// Splat's column pass of a group's sum: fine row yy takes camera row (yy + sy) / k.
fn splat_cols(out: &mut [f32], rows: &[f32], sy: i64, h: usize, k: usize) {
    let fw = rows.len() / h;
    let fh = (h * k) as i64;
    out.par_chunks_mut(fw)
        .with_min_len(rows_per_task(fw))
        .enumerate()
        .for_each(|(yy, dst)| {
            let f = yy as i64 + sy;
            if !(0..fh).contains(&f) {
                return;
            }
            let r = &rows[(f / k as i64) as usize * fw..][..fw];
            for (d, v) in dst.iter_mut().zip(r) {
                *d += v;
            }
        });
}

/// A flushed splat group's counts added to the weight plane (fine rows it reaches).
fn splat_weight(weight: &mut [f32], count_x: &[f32], sy: i64, fh: usize) {
    let fw = count_x.len();
    weight
        .par_chunks_mut(fw)
        .with_min_len(rows_per_task(fw))
        .enumerate()
        .for_each(|(yy, dst)| {
            if (0..fh as i64).contains(&(yy as i64 + sy)) {
                for (d, c) in dst.iter_mut().zip(count_x) {
                    *d += c;
                }
            }
        });
}

#[cfg(test)]
mod tests {
    use super::super::reconstruct::{interp_naive, splat_naive};
    use super::*;

    fn pattern(w: usize, h: usize, seed: u32) -> Vec<f32> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                let r = ((i as u32 ^ seed).wrapping_mul(2654435761) >> 24) as f32;
                100.0 + 60.0 * (0.7 * x + 0.3 * y + seed as f32).sin() + 0.3 * r
            })
            .collect()
    }

    fn max_diff(a: &Fine, b: &Fine) -> f32 {
        assert_eq!((a.width, a.height), (b.width, b.height));
        let d = a.data.iter().zip(&b.data).map(|(x, y)| (x - y).abs());
        d.fold(0.0, f32::max)
    }

    /// Groups flushed because only one or two may be open give the literal methods' result:
    /// eight frames in four vertical shifts (one past the border), revisited out of order.
    #[test]
    fn flushing_groups_keeps_the_result() {
        let frames: Vec<Vec<f32>> = (0..8).map(|s| pattern(9, 7, s)).collect();
        let shifts = [
            [0, 0],
            [-3, 2],
            [4, -1],
            [-7, 0],
            [2, 2],
            [-25, -30],
            [1, -1],
            [5, 0],
        ];
        let views: Vec<View> = frames.iter().map(|f| View::new(f, 9, 7)).collect();
        for k in [1, 3, 4] {
            for method in [Method::Interp, Method::Splat] {
                let naive = match method {
                    Method::Interp => interp_naive(&views, &shifts, k),
                    Method::Splat => splat_naive(&views, &shifts, k),
                };
                for max_open in [1, 2, 8] {
                    let mut acc = Accumulator::new(method, 9, 7, k, max_open);
                    for (v, s) in views.iter().zip(&shifts) {
                        acc.add(*v, *s);
                        assert!(acc.open_groups() <= max_open);
                    }
                    assert_eq!(acc.flushed(), max_open < 4, "{method:?} k={k}");
                    let d = max_diff(&acc.finish(), &naive);
                    // The fused and the literal methods agree to 1e-3 DN (f32 sums of
                    // ~200 DN); flushing only reorders the sums.
                    assert!(d < 1e-3, "{method:?} k={k} max_open={max_open}: {d}");
                }
            }
        }
    }

    /// A reconstruction computed only on a lattice holds, on it, exactly the whole one's
    /// values (with and without flushed groups), and zeros elsewhere.
    #[test]
    fn a_lattice_is_bit_for_bit_the_whole_reconstruction() {
        let frames: Vec<Vec<f32>> = (0..6).map(|s| pattern(11, 8, s)).collect();
        let shifts = [[0, 0], [-3, 2], [4, -1], [-7, 0], [2, 2], [1, -1]];
        let k = 10;
        for (lattice, max_open) in [([3, 1], 8), ([0, 4], 8), ([4, 2], 2)] {
            let lattice = Lattice {
                step: 5,
                phase: lattice,
            };
            let build = |only: Option<Lattice>| {
                let mut acc = Accumulator::new(Method::Interp, 11, 8, k, max_open);
                if let Some(l) = only {
                    acc = acc.only_at(l);
                }
                for (f, s) in frames.iter().zip(&shifts) {
                    acc.add(View::new(f, 11, 8), *s);
                }
                acc.finish()
            };
            let (whole, some) = (build(None), build(Some(lattice)));
            let mut on = 0;
            for (i, (w, s)) in whole.data.iter().zip(&some.data).enumerate() {
                let (x, y) = (i % whole.width, i / whole.width);
                if x % 5 == lattice.phase[0] && y % 5 == lattice.phase[1] {
                    assert_eq!(w.to_bits(), s.to_bits(), "({x}, {y}) on {lattice:?}");
                    on += 1;
                } else {
                    assert_eq!(*s, 0.0, "({x}, {y}) off {lattice:?}");
                }
            }
            assert_eq!(on, (110 / 5) * (80 / 5));
        }
    }

    #[test]
    fn a_reused_buffer_gives_the_fresh_result() {
        let frames: Vec<Vec<f32>> = (0..4).map(|s| pattern(9, 7, s)).collect();
        let shifts = [[0, 0], [-3, 2], [4, -1], [2, 2]];
        for (method, only) in [
            (Method::Interp, None),
            (Method::Interp, Some([2, 3])),
            (Method::Splat, None),
        ] {
            let build = || {
                let mut acc = Accumulator::new(method, 9, 7, 6, 8);
                if let Some(phase) = only {
                    acc = acc.only_at(Lattice { step: 3, phase });
                }
                for (f, s) in frames.iter().zip(&shifts) {
                    acc.add(View::new(f, 9, 7), *s);
                }
                acc
            };
            let fresh = build().finish();
            // Another reconstruction's leftovers, and more room than needed.
            let dirty = vec![f32::NAN; fresh.data.len() + 100];
            let reused = build().finish_in(dirty);
            assert_eq!(reused.data.len(), fresh.data.len(), "{method:?} {only:?}");
            let bits = |d: &[f32]| d.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&reused.data), bits(&fresh.data), "{method:?} {only:?}");
        }
    }
}
