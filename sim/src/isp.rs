//! The sensor and the camera's image processing: a Bayer mosaic with colour crosstalk (noise
//! is drawn per mosaic sample, as the sensor has one), demosaicing, lens-shading correction,
//! the sRGB curve and an unsharp mask on luma (the halos of a webcam's sharpening).
//!
//! Frames pass through here only when the camera has one of these effects
//! (`CameraModel::needs_isp`); the ideal camera goes straight from expected DN to 8 bits.

use crate::camera::{CameraModel, Cfa, Demosaic, Gamma};
use rayon::prelude::*;

/// Raw samples are quantised to 10 bits over the 8-bit range (0.25 DN steps).
pub const RAW_STEP_DN: f32 = 0.25;

/// The channel a Bayer RGGB pixel samples: red at (even, even), blue at (odd, odd).
#[inline]
pub fn cfa_channel(x: usize, y: usize) -> usize {
    match (x & 1, y & 1) {
        (0, 0) => 0,
        (1, 1) => 2,
        _ => 1,
    }
}

/// What a pixel filtered for `channel` responds to, with crosstalk `c` from the other two.
#[inline]
pub fn mixed(rgb: &[f32], channel: usize, c: f32) -> f32 {
    (1.0 - 3.0 * c) * rgb[channel] + c * (rgb[0] + rgb[1] + rgb[2])
}

/// Reflect an index into 0..n keeping its parity (the mosaic's pattern) at both ends.
#[inline]
fn refl(i: isize, n: usize) -> usize {
    let n = n as isize;
    let j = if i < 0 {
        -i
    } else if i >= n {
        2 * (n - 1) - i
    } else {
        i
    };
    j.clamp(0, n - 1) as usize
}

/// A plane padded by `pad` pixels on every side, reflected (parity kept), so neighbours are
/// read without bounds logic.
struct Padded {
    data: Vec<f32>,
    stride: usize,
    pad: usize,
}

impl Padded {
    fn new(plane: &[f32], w: usize, h: usize, pad: usize) -> Padded {
        let stride = w + 2 * pad;
        let mut data = vec![0f32; stride * (h + 2 * pad)];
        data.par_chunks_mut(stride)
            .enumerate()
            .for_each(|(py, row)| {
                let y = refl(py as isize - pad as isize, h);
                for (px, v) in row.iter_mut().enumerate() {
                    *v = plane[y * w + refl(px as isize - pad as isize, w)];
                }
            });
        Padded { data, stride, pad }
    }

    /// Index of pixel (x, y) of the original plane.
    #[inline]
    fn idx(&self, x: usize, y: usize) -> usize {
        (y + self.pad) * self.stride + x + self.pad
    }
}

/// Demosaic an RGGB mosaic (`w`x`h`) into interleaved linear RGB.
pub fn demosaic(raw: &[f32], w: usize, h: usize, method: Demosaic) -> Vec<f32> {
    let p = Padded::new(raw, w, h, 2);
    let (r, st) = (&p.data, p.stride);
    // Green everywhere first.
    let mut green = vec![0f32; w * h];
    green.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, g) in row.iter_mut().enumerate() {
            let i = p.idx(x, y);
            *g = if cfa_channel(x, y) == 1 {
                r[i]
            } else {
                let (l, rt, u, d) = (r[i - 1], r[i + 1], r[i - st], r[i + st]);
                match method {
                    Demosaic::Bilinear => 0.25 * (l + rt + u + d),
                    Demosaic::EdgeAware => {
                        // Hamilton–Adams: interpolate along the smoother direction, corrected
                        // by the sampled channel's second difference.
                        let c = r[i];
                        let lap_h = 2.0 * c - r[i - 2] - r[i + 2];
                        let lap_v = 2.0 * c - r[i - 2 * st] - r[i + 2 * st];
                        let dh = (l - rt).abs() + lap_h.abs();
                        let dv = (u - d).abs() + lap_v.abs();
                        let gh = 0.5 * (l + rt) + 0.25 * lap_h;
                        let gv = 0.5 * (u + d) + 0.25 * lap_v;
                        if dh < dv {
                            gh
                        } else if dv < dh {
                            gv
                        } else {
                            0.5 * (gh + gv)
                        }
                    }
                }
            };
        }
    });
    // Red and blue: bilinear in the difference to green (plain bilinear demosaicing is the
    // same with green taken as 0).
    let diff: Vec<f32> = match method {
        Demosaic::Bilinear => raw.to_vec(),
        Demosaic::EdgeAware => raw.par_iter().zip(&green).map(|(a, g)| a - g).collect(),
    };
    let q = Padded::new(&diff, w, h, 1);
    let (d, st) = (&q.data, q.stride);
    let mut out = vec![0f32; w * h * 3];
    out.par_chunks_mut(w * 3).enumerate().for_each(|(y, row)| {
        for x in 0..w {
            let i = q.idx(x, y);
            let base = match method {
                Demosaic::Bilinear => 0.0,
                Demosaic::EdgeAware => green[y * w + x],
            };
            let own = raw[y * w + x];
            let (r, b) = match (x & 1, y & 1) {
                (0, 0) | (1, 1) => {
                    let diag =
                        0.25 * (d[i - st - 1] + d[i - st + 1] + d[i + st - 1] + d[i + st + 1]);
                    if x & 1 == 0 {
                        (own, base + diag)
                    } else {
                        (base + diag, own)
                    }
                }
                (1, 0) => (
                    base + 0.5 * (d[i - 1] + d[i + 1]),
                    base + 0.5 * (d[i - st] + d[i + st]),
                ),
                _ => (
                    base + 0.5 * (d[i - st] + d[i + st]),
                    base + 0.5 * (d[i - 1] + d[i + 1]),
                ),
            };
            row[x * 3] = r;
            row[x * 3 + 1] = green[y * w + x];
            row[x * 3 + 2] = b;
        }
    });
    out
}

/// Steps per DN of the sRGB table.
const PER_DN: f32 = 64.0;

/// The sRGB curve of linear 8-bit DN, tabulated (the power function is too slow for millions
/// of samples): 64 steps per DN, linear interpolation (error < 0.01 DN).
fn srgb_table() -> &'static [f32] {
    static TABLE: std::sync::OnceLock<Vec<f32>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        (0..=256 * PER_DN as usize + 1)
            .map(|i| {
                let l = i as f64 / PER_DN as f64 / 255.0;
                let e = if l <= 0.003_130_8 {
                    12.92 * l
                } else {
                    1.055 * l.powf(1.0 / 2.4) - 0.055
                };
                (255.0 * e) as f32
            })
            .collect()
    })
}

/// The sRGB curve of one linear value in 8-bit DN through table `t`.
#[inline]
fn srgb_dn(t: &[f32], lin_dn: f32) -> f32 {
    let x = lin_dn.clamp(0.0, 255.0) * PER_DN;
    let i = x as usize;
    let f = x - i as f32;
    t[i] + (t[i + 1] - t[i]) * f
}

/// The sRGB curve (public for tests and the CRB): linear 8-bit DN in, encoded DN out.
pub fn srgb_encode_dn(lin_dn: f64) -> f64 {
    srgb_dn(srgb_table(), lin_dn as f32) as f64
}

/// Gaussian blur of a `w`x`h` plane (separable, reflecting borders).
fn blur(plane: &[f32], w: usize, h: usize, sigma: f64) -> Vec<f32> {
    let r = (3.0 * sigma).ceil() as usize;
    let k: Vec<f32> = (0..=2 * r)
        .map(|i| (-0.5 * ((i as f64 - r as f64) / sigma).powi(2)).exp() as f32)
        .collect();
    let sum: f32 = k.iter().sum();
    let k: Vec<f32> = k.iter().map(|v| v / sum).collect();
    let p = Padded::new(plane, w, h, r);
    // Horizontal pass over the padded rows (all of them, for the vertical pass).
    let mut tmp = vec![0f32; p.stride * (h + 2 * r)];
    tmp.par_chunks_mut(p.stride)
        .zip(p.data.par_chunks(p.stride))
        .for_each(|(o, src)| {
            for x in r..r + w {
                o[x] = k.iter().zip(&src[x - r..=x + r]).map(|(a, b)| a * b).sum();
            }
        });
    let mut out = vec![0f32; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (j, kv) in k.iter().enumerate() {
            let src = &tmp[(y + j) * p.stride + r..][..w];
            for (o, s) in row.iter_mut().zip(src) {
                *o += kv * s;
            }
        }
    });
    out
}

/// Linear RGB (8-bit DN scale, interleaved `w`x`h`) through the camera's processing to 8-bit
/// RGB: lens-shading correction, the output curve, sharpening on luma.
pub fn process(mut rgb: Vec<f32>, w: usize, h: usize, cam: &CameraModel) -> Vec<u8> {
    let corr = cam.vignetting_correction * cam.vignetting;
    let srgb = (cam.gamma == Gamma::Srgb).then(srgb_table);
    // Lens-shading gain: r² = (du² + dv²)/2, separable in its terms.
    let du2: Vec<f64> = (0..w)
        .map(|x| cam.radius2(x as f64, (h as f64 - 1.0) / 2.0))
        .collect();
    rgb.par_chunks_mut(w * 3).enumerate().for_each(|(y, row)| {
        let dv2 = cam.radius2((w as f64 - 1.0) / 2.0, y as f64);
        for x in 0..w {
            let gain = if corr > 0.0 {
                (1.0 / (1.0 - corr * (du2[x] + dv2))) as f32
            } else {
                1.0
            };
            for v in &mut row[x * 3..x * 3 + 3] {
                let l = *v * gain;
                *v = match srgb {
                    Some(t) => srgb_dn(t, l),
                    None => l.clamp(0.0, 255.0),
                };
            }
        }
    });
    let amount = cam.sharpen_amount as f32;
    let detail = (amount > 0.0).then(|| {
        let luma: Vec<f32> = rgb
            .par_chunks(3)
            .map(|p| 0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2])
            .collect();
        let b = blur(&luma, w, h, cam.sharpen_sigma_px);
        luma.iter()
            .zip(&b)
            .map(|(y, b)| amount * (y - b))
            .collect::<Vec<f32>>()
    });
    let mut out = vec![0u8; w * h * 3];
    out.par_chunks_mut(w * 3).enumerate().for_each(|(y, row)| {
        let src = &rgb[y * w * 3..(y + 1) * w * 3];
        for (x, (o, p)) in row.chunks_mut(3).zip(src.chunks(3)).enumerate() {
            let d = detail.as_ref().map_or(0.0, |d| d[y * w + x]);
            for k in 0..3 {
                // Round half up by truncation after the clamp, as `render::noise_row`.
                o[k] = ((p[k] + d).clamp(0.0, 255.0) + 0.5) as u8;
            }
        }
    });
    out
}

/// Whether frames of `cam` are mosaicked.
pub fn bayer(cam: &CameraModel) -> bool {
    cam.cfa == Cfa::Rggb
}
