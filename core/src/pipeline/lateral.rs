//! Lateral colour: a lens images red, green and blue at slightly different magnifications,
//! so away from the frame centre the channels of one edge lie a fraction of a pixel apart
//! (a webcam's corners: 0.2–1 px). The measurement plane mixes the channels
//! ([`super::plane::Mix`]); mixed unregistered, an edge becomes two edges, a blur along the
//! radius only, which the fit's round blur takes as misfit. Here: the model (each channel
//! sees what green sees at `x + m_c·(x − c) + t_c`), the registration of a channel onto
//! green while a plane is built, and the measurement of `m_c`, `t_c` from a calibration
//! scan's frames ([`channel_shift_px`] per target and frame, [`LateralFit`] over them).

use super::plane::Roi;
use super::reconstruct::cubic_weights;
use serde::{Deserialize, Serialize};

/// Where each channel images what green images at `x`: `x + m_c·(x − centre) + t_c`
/// (px). Green's own entry is zero.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LateralColour {
    /// The frame point the magnifications are about (px): the frame's middle.
    pub centre_px: [f64; 2],
    /// Per channel (R, G, B): its magnification against green, less 1.
    pub magnification: [f64; 3],
    /// Per channel: its shift against green at `centre_px`, px.
    pub shift_px: [[f64; 2]; 3],
}

/// Channels whose displacement stays under this everywhere in the frame are read as they
/// are (a thousandth of a pixel: far below what moves a fit).
const NEGLIGIBLE_PX: f64 = 1e-3;

impl LateralColour {
    /// Channel `c`'s displacement from green along `axis` at coordinate `v` of that axis.
    #[inline]
    pub fn delta_px(&self, c: usize, axis: usize, v: f64) -> f64 {
        self.magnification[c] * (v - self.centre_px[axis]) + self.shift_px[c][axis]
    }

    /// Whether channel `c` is displaced by a measurable amount anywhere in a `width` x
    /// `height` frame.
    pub fn moves(&self, c: usize, (width, height): (usize, usize)) -> bool {
        let corner = |axis: usize, n: usize| {
            let ends = [0.0, n.saturating_sub(1) as f64];
            ends.map(|v| self.delta_px(c, axis, v).abs())
                .into_iter()
                .fold(0.0, f64::max)
        };
        corner(0, width).max(corner(1, height)) > NEGLIGIBLE_PX
    }
}

/// The four rows (or columns) and cubic weights that sample position `s` on an axis of `n`
/// pixels, clamped to it.
#[inline]
fn taps(s: f64, n: usize) -> ([usize; 4], [f32; 4]) {
    let i = s.floor();
    let w = cubic_weights(s - i);
    let last = n as i64 - 1;
    let at = |o: i64| (i as i64 + o).clamp(0, last) as usize;
    ([at(-1), at(0), at(1), at(2)], w.map(|v| v as f32))
}

/// Channel `c` of `img` (interleaved RGB, `iw` x `ih`) registered onto green over the pixels
/// `x0..x1` x `y0..y1`, decoded through `lut`, times `weight`, added to `out` (row-major,
/// `x1 − x0` wide). The displacement along x depends on x alone and along y on y alone, so
/// each column's and each row's taps are computed once.
pub(super) fn add_registered(
    (raw, iw, ih): (&[u8], usize, usize),
    (c, weight): (usize, f32),
    lat: &LateralColour,
    lut: &[f32; 256],
    [x0, y0, x1, y1]: [usize; 4],
    out: &mut [f32],
) {
    let cols: Vec<_> = (x0..x1)
        .map(|x| taps(x as f64 + lat.delta_px(c, 0, x as f64), iw))
        .collect();
    let width = x1 - x0;
    for y in y0..y1 {
        let (rows, wy) = taps(y as f64 + lat.delta_px(c, 1, y as f64), ih);
        let line = &mut out[(y - y0) * width..(y - y0 + 1) * width];
        for (o, (cx, wx)) in line.iter_mut().zip(&cols) {
            let mut v = 0.0f32;
            for (&r, &w_r) in rows.iter().zip(&wy) {
                let row = &raw[r * iw * 3..(r + 1) * iw * 3];
                let h: f32 = (cx.iter().zip(wx))
                    .map(|(&x, &w_x)| w_x * lut[row[x * 3 + c] as usize])
                    .sum();
                v += w_r * h;
            }
            *o += weight * v;
        }
    }
}

/// How far channel `c` of `img` lies from green inside `roi` (px, `x_c − x_green`), by
/// Lucas–Kanade: the channel as green's contrast and level (`α·G(x − δ) + β`, the ink
/// darkens the channels by different amounts), refined until the step is under 1e-4 px.
/// Both decoded through `lut`. `None` when the window has no edges to register by.
pub fn channel_shift_px(
    img: &image::RgbImage,
    c: usize,
    roi: Roi,
    lut: &[f32; 256],
) -> Option<[f64; 2]> {
    let (iw, ih) = (img.width() as usize, img.height() as usize);
    if !roi.fits_in(iw, ih) || roi.w < 8 || roi.h < 8 {
        return None;
    }
    let raw = img.as_raw();
    let at = |ch: usize, x: usize, y: usize| lut[raw[(y * iw + x) * 3 + ch] as usize] as f64;
    let (x0, y0) = (roi.x as usize, roi.y as usize);
    let (x1, y1) = (x0 + roi.w as usize, y0 + roi.h as usize);
    let mut d = [0.0f64; 2];
    for _ in 0..8 {
        // Green moved by δ, at the window's inner pixels (its gradient needs neighbours).
        let shifted = LateralColour {
            centre_px: [0.0; 2],
            magnification: [0.0; 3],
            shift_px: [[0.0; 2], [-d[0], -d[1]], [0.0; 2]],
        };
        let (w, h) = (x1 - x0, y1 - y0);
        let mut g = vec![0.0f32; w * h];
        add_registered(
            (raw, iw, ih),
            (1, 1.0),
            &shifted,
            lut,
            [x0, y0, x1, y1],
            &mut g,
        );
        let gv = |x: usize, y: usize| g[(y - y0) * w + (x - x0)] as f64;
        // Normal equations of v_c ≈ α·G + β − α·∇G·Δ, unknowns (α, β, αΔx, αΔy).
        let mut n = nalgebra::Matrix4::<f64>::zeros();
        let mut r = nalgebra::Vector4::<f64>::zeros();
        for y in y0 + 1..y1 - 1 {
            for x in x0 + 1..x1 - 1 {
                let gx = 0.5 * (gv(x + 1, y) - gv(x - 1, y));
                let gy = 0.5 * (gv(x, y + 1) - gv(x, y - 1));
                let row = nalgebra::Vector4::new(gv(x, y), 1.0, -gx, -gy);
                n += row * row.transpose();
                r += row * at(c, x, y);
            }
        }
        let sol = n.cholesky()?.solve(&r);
        if sol[0].abs() < 1e-6 {
            return None;
        }
        let step = [sol[2] / sol[0], sol[3] / sol[0]];
        d = [d[0] + step[0], d[1] + step[1]];
        if step[0].hypot(step[1]) < 1e-4 {
            return Some(d);
        }
        if d[0].hypot(d[1]) > 3.0 {
            return None;
        }
    }
    Some(d)
}

/// Running least squares of a channel's shifts against green, `δ = m·(x − centre) + t`
/// (unknowns m, t_x, t_y), over (target, frame) pairs.
#[derive(Debug, Clone, Default)]
pub struct LateralFit {
    n: nalgebra::Matrix3<f64>,
    r: nalgebra::Vector3<f64>,
    rr: f64,
    count: usize,
}

impl LateralFit {
    /// One measured shift `d_px` at frame position `at_px` (both axes: two equations).
    pub fn add(&mut self, at_px: [f64; 2], centre_px: [f64; 2], d_px: [f64; 2]) {
        for axis in 0..2 {
            let mut row = nalgebra::Vector3::zeros();
            row[0] = at_px[axis] - centre_px[axis];
            row[1 + axis] = 1.0;
            self.n += row * row.transpose();
            self.r += row * d_px[axis];
            self.rr += d_px[axis] * d_px[axis];
        }
        self.count += 1;
    }

    /// `(m, t, u_m)`: the magnification (less 1), the shift at the centre and m's standard
    /// uncertainty from the residuals; `None` with fewer than 3 shifts or no spread in
    /// position.
    pub fn solve(&self) -> Option<(f64, [f64; 2], f64)> {
        if self.count < 3 {
            return None;
        }
        let inv = self.n.try_inverse()?;
        let p = inv * self.r;
        let dof = (2 * self.count).saturating_sub(3).max(1) as f64;
        let ssr = (self.rr - p.dot(&self.r)).max(0.0);
        let u_m = (inv[(0, 0)] * ssr / dof).sqrt();
        Some((p[0], [p[1], p[2]], u_m))
    }

    /// The RMS of the shifts (both axes) about `m`, `t`, px.
    fn residual_rms(&self, m: f64, t: [f64; 2]) -> f64 {
        let p = nalgebra::Vector3::new(m, t[0], t[1]);
        let ssr = self.rr - 2.0 * p.dot(&self.r) + (p.transpose() * self.n * p)[0];
        (ssr.max(0.0) / (2 * self.count).max(1) as f64).sqrt()
    }
}

/// A lens's lateral colour as a calibration scan measured it: what jobs register their
/// channels with, and how sure it is.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LateralColourFit {
    pub model: LateralColour,
    /// Per channel: the standard uncertainty of its magnification (0 for green, and for a
    /// channel left unregistered).
    pub magnification_u: [f64; 3],
    /// Per channel: the RMS of its measured shifts about the model, px.
    pub residual_rms_px: [f64; 3],
    /// Per channel: how many (target, frame) shifts it was fitted to; 0 for green, and for
    /// a channel left unregistered.
    pub shifts: [usize; 3],
}

/// The largest magnification (less 1) and shift a record may say: a lens with more
/// lateral colour than 1 % of the radius, or a channel 5 px off, is not what a scan of
/// this kind measures (a webcam's is ~4e-4 and ~0.02 px).
const MAX_MAGNIFICATION: f64 = 0.01;
const MAX_SHIFT_PX: f64 = 5.0;

impl LateralColourFit {
    /// Whether a record read back can be used: finite numbers within what a lens does,
    /// green the reference; else what is wrong, naming the field.
    pub fn check(&self) -> Result<(), String> {
        let m = &self.model;
        if !m.centre_px.iter().all(|v| v.is_finite()) {
            return Err(format!("centre_px {:?} is not finite", m.centre_px));
        }
        for c in 0..3 {
            let (mag, t) = (m.magnification[c], m.shift_px[c]);
            if !(mag.is_finite() && mag.abs() <= MAX_MAGNIFICATION) {
                return Err(format!(
                    "magnification[{c}] {mag} is not a number within ±{MAX_MAGNIFICATION}"
                ));
            }
            if !t.iter().all(|v| v.is_finite() && v.abs() <= MAX_SHIFT_PX) {
                return Err(format!(
                    "shift_px[{c}] {t:?} is not within ±{MAX_SHIFT_PX} px"
                ));
            }
        }
        if m.magnification[1] != 0.0 || m.shift_px[1] != [0.0; 2] {
            return Err("green (channel 1) is the reference: its entries must be 0".into());
        }
        Ok(())
    }
}

/// A channel is registered only when its magnification is known to this many pixels at
/// the frame's corner (a channel the ink barely darkens, red under red ink, is measured
/// too loosely to move by; its weight in the plane is small anyway).
const CORNER_U_PX: f64 = 0.02;

/// A calibration scan's lateral colour, measured frame by frame: each target's red and
/// blue images against its green one.
#[derive(Debug, Clone, Default)]
pub struct LateralScan {
    fits: [LateralFit; 3],
    frame_size: Option<(usize, usize)>,
}

impl LateralScan {
    /// The frame's red and blue shifts at each target (`(outer centre, rim radius)`, px),
    /// the channels decoded through `lut`.
    pub fn add_frame(
        &mut self,
        img: &image::RgbImage,
        lut: &[f32; 256],
        targets: &[([f64; 2], f64)],
    ) {
        let size = (img.width() as usize, img.height() as usize);
        self.frame_size = Some(size);
        let centre = centre_of(size);
        for &(at, rim) in targets {
            let half = rim + 4.0;
            let (x, y) = (at[0] - half, at[1] - half);
            if x < 0.0 || y < 0.0 {
                continue;
            }
            let side = (2.0 * half).ceil() as u32 + 1;
            let roi = Roi {
                x: x.floor() as u32,
                y: y.floor() as u32,
                w: side,
                h: side,
            };
            for c in [0, 2] {
                if let Some(d) = channel_shift_px(img, c, roi, lut) {
                    self.fits[c].add(at, centre, d);
                }
            }
        }
    }

    /// The fit, the channels measured too loosely (or not at all) left unregistered;
    /// `None` when no channel is registered.
    pub fn finish(&self) -> Option<LateralColourFit> {
        let size = self.frame_size?;
        let centre = centre_of(size);
        let corner = centre[0].hypot(centre[1]);
        let mut out = LateralColourFit {
            model: LateralColour {
                centre_px: centre,
                magnification: [0.0; 3],
                shift_px: [[0.0; 2]; 3],
            },
            magnification_u: [0.0; 3],
            residual_rms_px: [0.0; 3],
            shifts: [0; 3],
        };
        for c in [0, 2] {
            let Some((m, t, u_m)) = self.fits[c].solve() else {
                continue;
            };
            if u_m * corner > CORNER_U_PX {
                continue;
            }
            out.model.magnification[c] = m;
            out.model.shift_px[c] = t;
            out.magnification_u[c] = u_m;
            out.residual_rms_px[c] = self.fits[c].residual_rms(m, t);
            out.shifts[c] = self.fits[c].count;
        }
        (out.shifts.iter().any(|&n| n > 0)).then_some(out)
    }
}

/// The middle of a `width` x `height` frame (pixel centres at integers).
fn centre_of((w, h): (usize, usize)) -> [f64; 2] {
    [(w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::response::Response;

    /// A blurred disk of radius 9 px at `c`, dark in green and blue (blue's image at
    /// `c + db`), red flat.
    fn disk(c: [f64; 2], db: [f64; 2]) -> image::RgbImage {
        let level = |x: f64, y: f64, at: [f64; 2]| {
            let r = (x - at[0]).hypot(y - at[1]);
            let e = 0.5 * (1.0 + ((r - 9.0) / 1.2).tanh());
            (60.0 + 160.0 * e).round() as u8
        };
        image::RgbImage::from_fn(48, 40, |x, y| {
            let (x, y) = (x as f64, y as f64);
            let b = level(x, y, [c[0] + db[0], c[1] + db[1]]);
            image::Rgb([200, level(x, y, c), b])
        })
    }

    #[test]
    fn lucas_kanade_finds_the_blue_image_where_it_is() {
        let lut = Response::Linear.table();
        let roi = Roi {
            x: 4,
            y: 4,
            w: 40,
            h: 32,
        };
        for db in [[0.3, -0.2], [-0.15, 0.0], [0.0, 0.0]] {
            let img = disk([23.4, 19.7], db);
            let d = channel_shift_px(&img, 2, roi, lut).expect("edges to register by");
            // 8-bit rounding of the rendered levels leaves ~0.005 px.
            assert!(
                (d[0] - db[0]).abs() < 0.01 && (d[1] - db[1]).abs() < 0.01,
                "{d:?} vs {db:?}"
            );
        }
        // A flat channel has nothing to register by.
        assert!(channel_shift_px(&disk([23.4, 19.7], [0.0; 2]), 0, roi, lut).is_none());
    }

    #[test]
    fn registration_puts_a_displaced_channel_back_on_green() {
        let lut = Response::Linear.table();
        let (c, db) = ([23.4, 19.7], [0.35, -0.25]);
        let img = disk(c, db);
        let lat = LateralColour {
            centre_px: [0.0; 2],
            magnification: [0.0; 3],
            shift_px: [[0.0; 2], [0.0; 2], db],
        };
        let (w, h) = (img.width() as usize, img.height() as usize);
        let mut blue = vec![0.0f32; w * h];
        add_registered(
            (img.as_raw(), w, h),
            (2, 1.0),
            &lat,
            lut,
            [0, 0, w, h],
            &mut blue,
        );
        // Registered, blue is green (the same levels here) to within the cubic's error on
        // a sharp edge (2.5 DN) and the 8-bit rounding; unregistered it is off by ~25 DN.
        let worst = |f: &dyn Fn(usize, usize) -> f32| {
            (4..h - 4)
                .flat_map(|y| (4..w - 4).map(move |x| (x, y)))
                .map(|(x, y)| (f(x, y) - img.get_pixel(x as u32, y as u32)[1] as f32).abs())
                .fold(0.0f32, f32::max)
        };
        let registered = worst(&|x, y| blue[y * w + x]);
        let raw = worst(&|x, y| img.get_pixel(x as u32, y as u32)[2] as f32);
        assert!(
            registered < 4.0,
            "registered blue off green by {registered} DN"
        );
        assert!(raw > 15.0, "the test's displacement shows: {raw} DN");
    }

    #[test]
    fn the_fit_recovers_magnification_and_shift() {
        let (m, t, centre) = (-4e-4, [0.02, -0.01], [639.5, 359.5]);
        let mut fit = LateralFit::default();
        for (i, at) in [
            [100.0, 80.0],
            [1200.0, 90.0],
            [640.0, 360.0],
            [150.0, 650.0],
            [1180.0, 640.0],
        ]
        .into_iter()
        .enumerate()
        {
            let wobble = if i % 2 == 0 { 1e-3 } else { -1e-3 };
            let d = [0, 1].map(|a| m * (at[a] - centre[a]) + t[a] + wobble);
            fit.add(at, centre, d);
        }
        let (got_m, got_t, u_m) = fit.solve().unwrap();
        assert!((got_m - m).abs() < 5e-6, "{got_m}");
        assert!((got_t[0] - t[0]).abs() < 2e-3 && (got_t[1] - t[1]).abs() < 2e-3);
        assert!(u_m > 0.0 && u_m < 1e-5, "{u_m}");
        let lat = LateralColour {
            centre_px: centre,
            magnification: [0.0, 0.0, m],
            shift_px: [[0.0; 2], [0.0; 2], t],
        };
        assert!(lat.moves(2, (1280, 720)) && !lat.moves(1, (1280, 720)));
    }
}
