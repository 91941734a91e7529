//! Reconstruction on a k-times finer grid from frames displaced by known sub-pixel amounts.
//!
//! Fine-grid convention: fine pixel `X` (pixel centres at integers, as everywhere) has its
//! centre at low-resolution coordinate `x = (X + 0.5) / k - 0.5`, so the k x k fine pixels
//! of a camera pixel tile it exactly. A frame whose content is displaced by `d` px from
//! frame 0 (a feature at `p` in frame 0 is at `p + d` in it) is shifted by
//! `s = round(d * k)` fine pixels, the paper's "shift on the fine grid".
//!
//! Two reconstructions:
//! - [`interp`], the paper's: upsample each frame by k with a cubic kernel, shift it by `s`,
//!   average. Done fused and separable: the upsampled frames are never built. Each frame is
//!   resampled once along rows (a cubic weight set per sub-pixel phase, k phases), frames
//!   with the same vertical shift are summed, and each such group is resampled once along
//!   columns. [`interp_naive`] is the literal method, kept as the reference the tests hold
//!   the fused one to. The row passes are summed as frames arrive
//!   ([`super::accumulate::Accumulator`]): no frame is kept.
//! - [`splat`], direct shift-and-add: every camera pixel is added onto the k x k fine
//!   pixels it covers at its shifted place, and each fine pixel is divided by how many
//!   camera pixels landed on it. Separable the same way; [`splat_naive`] is the reference.
//!
//! Borders replicate (a sample left of column 0 reads column 0), as Matlab's and OpenCV's
//! resize do, so every fine pixel of `interp` gets every frame.

use super::accumulate::{Accumulator, Method};

/// A read-only view of one channel of a frame (row-major, `width * height` samples).
#[derive(Debug, Clone, Copy)]
pub struct View<'a> {
    pub data: &'a [f32],
    pub width: usize,
    pub height: usize,
}

impl<'a> View<'a> {
    pub fn new(data: &'a [f32], width: usize, height: usize) -> View<'a> {
        assert_eq!(data.len(), width * height, "view size");
        View {
            data,
            width,
            height,
        }
    }

    #[inline]
    pub(crate) fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }
}

/// A reconstruction: `width = k * camera width`, same for height.
#[derive(Debug, Clone, PartialEq)]
pub struct Fine {
    pub width: usize,
    pub height: usize,
    pub k: usize,
    pub data: Vec<f32>,
}

impl Fine {
    /// As a 16-bit grey image: camera DN 0..255 map onto 0..65535 (x257), clamped.
    pub fn to_png16(&self) -> image::ImageBuffer<image::Luma<u16>, Vec<u16>> {
        let px = self
            .data
            .iter()
            .map(|&v| (v as f64 * 257.0).round().clamp(0.0, 65535.0) as u16)
            .collect();
        image::ImageBuffer::from_raw(self.width as u32, self.height as u32, px)
            .expect("buffer matches the size")
    }
}

/// The fine-grid shift of a displacement: `round(d * k)` fine pixels per axis.
pub fn fine_shift(d_px: [f64; 2], k: usize) -> [i64; 2] {
    [
        (d_px[0] * k as f64).round() as i64,
        (d_px[1] * k as f64).round() as i64,
    ]
}

/// Keys' cubic convolution kernel with a = -0.5 (Matlab's `imresize` bicubic, which the
/// paper used): weights of the four samples at offsets -1, 0, 1, 2 for a fraction `t`.
#[inline]
pub fn cubic_weights(t: f64) -> [f64; 4] {
    const A: f64 = -0.5;
    let w = |d: f64| -> f64 {
        let d = d.abs();
        if d <= 1.0 {
            ((A + 2.0) * d - (A + 3.0)) * d * d + 1.0
        } else if d < 2.0 {
            ((A * d - 5.0 * A) * d + 8.0 * A) * d - 4.0 * A
        } else {
            0.0
        }
    };
    [w(1.0 + t), w(t), w(1.0 - t), w(2.0 - t)]
}

/// Where fine sample `f` (already shifted, on a fine axis of `n * k` samples) reads from the
/// camera axis of `n` samples: four clamped indices and their cubic weights.
#[derive(Clone, Copy)]
pub(crate) struct Taps {
    pub(crate) idx: [u32; 4],
    pub(crate) w: [f32; 4],
}

fn taps(f: i64, n: usize, k: usize) -> Taps {
    let f = f.clamp(0, (n * k) as i64 - 1);
    let x = (f as f64 + 0.5) / k as f64 - 0.5;
    let x0 = x.floor();
    let w = cubic_weights(x - x0);
    let mut t = Taps {
        idx: [0; 4],
        w: [0.0; 4],
    };
    for (j, (i, wt)) in t.idx.iter_mut().zip(&mut t.w).enumerate() {
        *i = (x0 as i64 - 1 + j as i64).clamp(0, n as i64 - 1) as u32;
        *wt = w[j] as f32;
    }
    t
}

/// The table of taps of one fine axis for the shift `s`. Only k phases exist, but a table
/// per output sample keeps the inner loops free of divisions and clamps.
pub(crate) fn tap_table(n: usize, k: usize, s: i64) -> Vec<Taps> {
    (0..(n * k) as i64).map(|f| taps(f + s, n, k)).collect()
}

fn check(frames: &[View], shifts: &[[i64; 2]], k: usize) -> (usize, usize) {
    assert!(k >= 1, "k >= 1");
    assert!(!frames.is_empty(), "at least one frame");
    assert_eq!(frames.len(), shifts.len(), "one shift per frame");
    let (w, h) = (frames[0].width, frames[0].height);
    for f in frames {
        assert!(f.width == w && f.height == h, "frames of one size");
    }
    (w, h)
}

/// The paper's reconstruction, fused and separable. `shifts` are fine-grid shifts
/// ([`fine_shift`]). The frames are added one by one to an [`Accumulator`], which is what
/// the pipeline does as they arrive.
pub fn interp(frames: &[View], shifts: &[[i64; 2]], k: usize) -> Fine {
    batch(Method::Interp, frames, shifts, k)
}

/// All frames through one [`Accumulator`] that keeps every group (none flushed).
fn batch(method: Method, frames: &[View], shifts: &[[i64; 2]], k: usize) -> Fine {
    let (w, h) = check(frames, shifts, k);
    let mut acc = Accumulator::new(method, w, h, k, usize::MAX);
    for (f, s) in frames.iter().zip(shifts) {
        acc.add(*f, *s);
    }
    acc.finish()
}

/// The paper's method literally: build each upsampled frame (2-D cubic, 16 taps per fine
/// pixel), shift it on the fine grid, average. Slow; the reference for [`interp`].
pub fn interp_naive(frames: &[View], shifts: &[[i64; 2]], k: usize) -> Fine {
    let (w, h) = check(frames, shifts, k);
    let (fw, fh) = (w * k, h * k);
    let mut out = vec![0f64; fw * fh];
    for (f, s) in frames.iter().zip(shifts) {
        // Upsample.
        let mut up = vec![0f64; fw * fh];
        for yy in 0..fh {
            let ty = taps(yy as i64, h, k);
            for xx in 0..fw {
                let tx = taps(xx as i64, w, k);
                let mut v = 0.0;
                for (&iy, &wy) in ty.idx.iter().zip(&ty.w) {
                    for (&ix, &wx) in tx.idx.iter().zip(&tx.w) {
                        v += wy as f64 * wx as f64 * f.at(ix as usize, iy as usize) as f64;
                    }
                }
                up[yy * fw + xx] = v;
            }
        }
        // Shift (replicating the border) and add.
        for yy in 0..fh {
            let sy = (yy as i64 + s[1]).clamp(0, fh as i64 - 1) as usize;
            for xx in 0..fw {
                let sx = (xx as i64 + s[0]).clamp(0, fw as i64 - 1) as usize;
                out[yy * fw + xx] += up[sy * fw + sx];
            }
        }
    }
    let n = frames.len() as f64;
    Fine {
        width: fw,
        height: fh,
        k,
        data: out.into_iter().map(|v| (v / n) as f32).collect(),
    }
}

/// Direct shift-and-add, separable. A fine pixel no camera pixel landed on (only at the
/// border, where shifted frames do not reach) takes frame 0's value.
pub fn splat(frames: &[View], shifts: &[[i64; 2]], k: usize) -> Fine {
    batch(Method::Splat, frames, shifts, k)
}

/// Shift-and-add literally: each camera pixel added onto its k x k fine footprint. Slow;
/// the reference for [`splat`].
pub fn splat_naive(frames: &[View], shifts: &[[i64; 2]], k: usize) -> Fine {
    let (w, h) = check(frames, shifts, k);
    let (fw, fh) = (w * k, h * k);
    let mut acc = vec![0f64; fw * fh];
    let mut n = vec![0u32; fw * fh];
    for (f, s) in frames.iter().zip(shifts) {
        for y in 0..h {
            for x in 0..w {
                for b in 0..k as i64 {
                    for a in 0..k as i64 {
                        let (fx, fy) = ((x * k) as i64 - s[0] + a, (y * k) as i64 - s[1] + b);
                        if (0..fw as i64).contains(&fx) && (0..fh as i64).contains(&fy) {
                            let i = fy as usize * fw + fx as usize;
                            acc[i] += f.at(x, y) as f64;
                            n[i] += 1;
                        }
                    }
                }
            }
        }
    }
    let data = (0..fw * fh)
        .map(|i| {
            if n[i] > 0 {
                (acc[i] / n[i] as f64) as f32
            } else {
                frames[0].at((i % fw) / k, (i / fw) / k)
            }
        })
        .collect();
    Fine {
        width: fw,
        height: fh,
        k,
        data,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic test pattern with structure at all scales.
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
        a.data
            .iter()
            .zip(&b.data)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    }

    fn frames_and_shifts() -> (Vec<Vec<f32>>, Vec<[i64; 2]>) {
        let frames: Vec<Vec<f32>> = (0..5).map(|s| pattern(9, 7, s)).collect();
        // Mixed x shifts, two different y shifts (two column-pass groups), one beyond the
        // border so clamping is exercised.
        let shifts = vec![[0, 0], [-3, 0], [-7, 2], [4, 2], [-25, -1]];
        (frames, shifts)
    }

    #[test]
    fn cubic_weights_sum_to_one_and_interpolate() {
        for t in [0.0, 0.1, 0.37, 0.5, 0.99] {
            let w = cubic_weights(t);
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        }
        assert_eq!(cubic_weights(0.0), [0.0, 1.0, 0.0, 0.0]);
        // A linear ramp is reproduced exactly.
        let w = cubic_weights(0.3);
        let v: f64 = w
            .iter()
            .zip([-1.0, 0.0, 1.0, 2.0])
            .map(|(a, b)| a * b)
            .sum();
        assert!((v - 0.3).abs() < 1e-12);
    }

    #[test]
    fn fused_interp_equals_upsample_shift_average() {
        let (frames, shifts) = frames_and_shifts();
        let views: Vec<View> = frames.iter().map(|f| View::new(f, 9, 7)).collect();
        for k in [1, 3, 5] {
            let fused = interp(&views, &shifts, k);
            let naive = interp_naive(&views, &shifts, k);
            let d = max_diff(&fused, &naive);
            assert!(d < 1e-3, "k={k}: fused and naive differ by {d}");
        }
    }

    #[test]
    fn fused_splat_equals_per_pixel_splat() {
        let (frames, shifts) = frames_and_shifts();
        let views: Vec<View> = frames.iter().map(|f| View::new(f, 9, 7)).collect();
        for k in [1, 4] {
            let d = max_diff(&splat(&views, &shifts, k), &splat_naive(&views, &shifts, k));
            assert!(d < 1e-3, "k={k}: splat differs by {d}");
        }
    }

    #[test]
    fn k1_without_shift_is_the_frame() {
        let f = pattern(6, 5, 3);
        let v = [View::new(&f, 6, 5)];
        assert_eq!(interp(&v, &[[0, 0]], 1).data, f);
        assert_eq!(splat(&v, &[[0, 0]], 1).data, f);
    }

    /// Frames of a 1-D edge displaced by known sub-pixel steps: the reconstruction puts the
    /// edge where it is in frame 0, to a fraction of a camera pixel.
    #[test]
    fn reconstruction_registers_a_moving_edge() {
        let (w, h, k) = (24, 3, 10);
        let edge_at = 11.3; // in frame 0
        let render = |d: f64| -> Vec<f32> {
            (0..w * h)
                .map(|i| {
                    let x = (i % w) as f64;
                    // Area-integrated unit step at edge_at + d.
                    let c = (x + 0.5 - (edge_at + d)).clamp(0.0, 1.0);
                    (50.0 + 150.0 * c) as f32
                })
                .collect()
        };
        let ds: Vec<f64> = (0..10).map(|i| -0.1 * i as f64).collect();
        let frames: Vec<Vec<f32>> = ds.iter().map(|&d| render(d)).collect();
        let views: Vec<View> = frames.iter().map(|f| View::new(f, w, h)).collect();
        let shifts: Vec<[i64; 2]> = ds.iter().map(|&d| fine_shift([d, 0.0], k)).collect();
        for fine in [interp(&views, &shifts, k), splat(&views, &shifts, k)] {
            let row = &fine.data[fine.width..2 * fine.width];
            // Half-level crossing, in camera px.
            let mid = 125.0;
            let i = row.iter().position(|&v| v >= mid).unwrap();
            let t = (mid - row[i - 1]) / (row[i] - row[i - 1]);
            let xf = (i - 1) as f64 + t as f64;
            let x = (xf + 0.5) / k as f64 - 0.5;
            assert!((x - edge_at).abs() < 0.08, "edge at {x}, want {edge_at}");
        }
    }

    #[test]
    fn png16_maps_dn_to_full_range() {
        let f = Fine {
            width: 2,
            height: 1,
            k: 1,
            data: vec![255.0, 1.0],
        };
        assert_eq!(f.to_png16().into_raw(), vec![65535, 257]);
    }
}
