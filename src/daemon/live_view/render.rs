//! A frame made into what a client sees: the targets found in it (the pipeline's detection
//! and estimator, and its focus figure) and its image cropped, scaled and PNG-encoded.

use super::wire::{ViewOptions, ViewTarget, MAX_FPS, MIN_FPS};
use crate::daemon::protocol::{ErrorCode, ProtoError};
use crate::pipeline::detect::{detect, measurement_channel, DetectConfig};
use crate::pipeline::estimate::estimate_targets;
use crate::pipeline::{focus, layout, Estimator};
use crate::rig::RigInfo;
use base64::Engine as _;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{ImageEncoder, RgbImage};

/// View options checked against the frame size: the crop inside it, the scale in (0, 1].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shown {
    pub crop: [u32; 4],
    pub scale: f64,
}

fn bad(msg: String) -> ProtoError {
    ProtoError::new(ErrorCode::BadRequest, msg)
}

impl Shown {
    pub fn check(o: &ViewOptions, frame: (u32, u32)) -> Result<Shown, ProtoError> {
        let scale = o.scale.unwrap_or(1.0);
        if !(scale.is_finite() && scale > 0.0 && scale <= 1.0) {
            return Err(bad(format!(
                "`scale` must be above 0 and at most 1, got {scale}"
            )));
        }
        let crop = o.crop.unwrap_or([0, 0, frame.0, frame.1]);
        let [x, y, w, h] = crop;
        let inside = w > 0
            && h > 0
            && x as u64 + w as u64 <= frame.0 as u64
            && y as u64 + h as u64 <= frame.1 as u64;
        if !inside {
            return Err(bad(format!(
                "`crop` [{x}, {y}, {w}, {h}] (x, y, width, height) must lie inside the {}x{} frame and not be empty",
                frame.0, frame.1
            )));
        }
        Ok(Shown { crop, scale })
    }

    /// The image's size: the crop times the scale, at least one pixel.
    pub fn size(&self) -> (u32, u32) {
        let s = |v: u32| ((v as f64 * self.scale).round() as u32).max(1);
        (s(self.crop[2]), s(self.crop[3]))
    }
}

/// A preview's rate: from [`MIN_FPS`] to [`MAX_FPS`] (NaN refused).
pub fn check_fps(max_fps: f64) -> Result<f64, ProtoError> {
    if (MIN_FPS..=MAX_FPS).contains(&max_fps) {
        Ok(max_fps)
    } else {
        Err(bad(format!(
            "`max_fps` must be from {MIN_FPS} to {MAX_FPS}, got {max_fps}"
        )))
    }
}

/// The shown part of `img` as base64 PNG (fast compression: the live view favours speed),
/// with its size. A crop reaching past a smaller frame (a replay's) is cut to it.
pub fn png_base64(img: &RgbImage, shown: &Shown) -> (String, u32, u32) {
    let part = shown_pixels(img, shown);
    let (sw, sh) = part.dimensions();
    let mut png = Vec::new();
    PngEncoder::new_with_quality(&mut png, CompressionType::Fast, FilterType::Sub)
        .write_image(part.as_raw(), sw, sh, image::ExtendedColorType::Rgb8)
        .expect("encoding a PNG into memory");
    (
        base64::engine::general_purpose::STANDARD.encode(png),
        sw,
        sh,
    )
}

/// The crop of `img`, scaled by an area average over whole source pixels: each shown pixel
/// is the mean of the block of frame pixels it covers (no aliasing of the rings' edges, and
/// one pass over the crop in integers, a few times faster than a filtered resize).
pub fn shown_pixels(img: &RgbImage, shown: &Shown) -> RgbImage {
    let [x, y, w, h] = shown.crop;
    let x = x.min(img.width().saturating_sub(1));
    let y = y.min(img.height().saturating_sub(1));
    let (w, h) = (
        w.min(img.width() - x).max(1),
        h.min(img.height() - y).max(1),
    );
    let s = |v: u32| ((v as f64 * shown.scale).round() as u32).clamp(1, v);
    let (sw, sh) = (s(w), s(h));
    // Block edges: shown pixel i covers frame columns edges[i]..edges[i + 1] (at least one).
    let edges = |n: u32, m: u32, o: u32| -> Vec<usize> {
        (0..=m)
            .map(|i| (o as u64 + i as u64 * n as u64 / m as u64) as usize)
            .collect()
    };
    let stride = img.width() as usize * 3;
    let raw = img.as_raw();
    if (sw, sh) == (w, h) {
        let (x, w) = (x as usize * 3, w as usize * 3);
        let rows = (y..y + h).map(|r| r as usize * stride);
        let out = rows.flat_map(|r| &raw[r + x..r + x + w]).copied().collect();
        return RgbImage::from_raw(sw, sh, out).expect("a buffer of the crop's size");
    }
    let (xs, ys) = (edges(w, sw, x), edges(h, sh, y));
    let mut out = Vec::with_capacity(sw as usize * sh as usize * 3);
    let mut acc = vec![0u32; sw as usize * 3];
    for oy in 0..sh as usize {
        acc.fill(0);
        for sy in ys[oy]..ys[oy + 1] {
            let row = &raw[sy * stride..(sy + 1) * stride];
            for (ox, a) in acc.chunks_exact_mut(3).enumerate() {
                for px in row[xs[ox] * 3..xs[ox + 1] * 3].chunks_exact(3) {
                    a[0] += px[0] as u32;
                    a[1] += px[1] as u32;
                    a[2] += px[2] as u32;
                }
            }
        }
        let rows = (ys[oy + 1] - ys[oy]) as u32;
        for (ox, a) in acc.chunks_exact(3).enumerate() {
            let n = rows * (xs[ox + 1] - xs[ox]) as u32;
            out.extend(a.iter().map(|&v| ((v + n / 2) / n) as u8));
        }
    }
    RgbImage::from_raw(sw, sh, out).expect("a buffer of the shown size")
}

/// The targets in `img`: detected, measured by the rig's estimator, named after its board,
/// each with its focus figure.
pub fn targets(img: &RgbImage, info: &RigInfo) -> Vec<ViewTarget> {
    targets_by(img, info, info.job_defaults.estimator.unwrap_or_default())
}

/// [`targets`] measured by `estimator`.
pub fn targets_by(img: &RgbImage, info: &RigInfo, estimator: Estimator) -> Vec<ViewTarget> {
    let det = detect(img, &DetectConfig::default());
    if det.targets.is_empty() {
        return Vec::new();
    }
    let channel = measurement_channel(img, &det);
    let ests = estimate_targets(img, &det, (channel, info.response), estimator);
    let found: Vec<[f64; 2]> = det.targets.iter().map(|c| c.outer_centre_px).collect();
    let names = match &info.board {
        Some(b) => layout::name_targets(&found, b, info.scale_um_per_px),
        None => vec![None; found.len()],
    };
    let s = info.scale_um_per_px;
    det.targets
        .iter()
        .zip(ests)
        .zip(names)
        .map(|((c, e), name)| {
            let (outer, inner, ro, ri, error) = match e {
                Ok(e) => (
                    e.outer_px,
                    e.inner_px,
                    e.outer_radius_px,
                    e.inner_radius_px,
                    None,
                ),
                Err(err) => (
                    c.outer_centre_px,
                    c.inner_centre_px,
                    c.outer_radii_px[1],
                    c.inner_radii_px[1],
                    Some(err.to_string()),
                ),
            };
            let f = focus::focus(img, channel, c);
            ViewTarget {
                name,
                centre_px: outer,
                centre_um: [outer[0] * s, outer[1] * s],
                offset_um: [(inner[0] - outer[0]) * s, (inner[1] - outer[1]) * s],
                outer_radius_px: ro,
                inner_radius_px: ri,
                focus: f,
                edge_sigma_px: f.map(focus::edge_sigma_px),
                error,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_are_checked_against_the_frame() {
        let ok = Shown::check(&ViewOptions::default(), (64, 48)).unwrap();
        assert_eq!(
            (ok.crop, ok.scale, ok.size()),
            ([0, 0, 64, 48], 1.0, (64, 48))
        );
        let o = ViewOptions {
            scale: Some(0.25),
            crop: Some([10, 8, 40, 20]),
        };
        assert_eq!(Shown::check(&o, (64, 48)).unwrap().size(), (10, 5));
        let e = Shown::check(
            &ViewOptions {
                crop: Some([30, 0, 40, 10]),
                ..o
            },
            (64, 48),
        )
        .unwrap_err();
        assert_eq!(
            e.message,
            "`crop` [30, 0, 40, 10] (x, y, width, height) must lie inside the 64x48 frame and not be empty"
        );
        for s in [0.0, 1.5, f64::NAN] {
            let e = Shown::check(
                &ViewOptions {
                    scale: Some(s),
                    crop: None,
                },
                (64, 48),
            )
            .unwrap_err();
            assert!(e.message.starts_with("`scale` must be above 0"), "{e:?}");
        }
        assert!(check_fps(0.0).is_err() && check_fps(61.0).is_err());
        for v in [1e-300, 5e-324, -0.0, 0.009, f64::NAN, f64::INFINITY, -1e308] {
            let e = check_fps(v).unwrap_err();
            assert!(
                e.message.contains("`max_fps` must be from 0.01 to 60"),
                "{v}: {e:?}"
            );
        }
        assert_eq!(check_fps(0.01), Ok(0.01));
        assert_eq!(check_fps(30.0), Ok(30.0));
    }

    #[test]
    fn the_png_decodes_at_the_shown_size() {
        let img = RgbImage::from_fn(64, 48, |x, y| image::Rgb([x as u8, y as u8, 9]));
        let shown = Shown {
            crop: [8, 4, 32, 20],
            scale: 0.5,
        };
        let png = base64::engine::general_purpose::STANDARD
            .decode(png_base64(&img, &shown).0)
            .unwrap();
        let back = image::load_from_memory(&png).unwrap().to_rgb8();
        assert_eq!(back.dimensions(), (16, 10));
        let full = Shown {
            crop: [8, 4, 32, 20],
            scale: 1.0,
        };
        let png = base64::engine::general_purpose::STANDARD
            .decode(png_base64(&img, &full).0)
            .unwrap();
        let back = image::load_from_memory(&png).unwrap().to_rgb8();
        assert_eq!(back.get_pixel(0, 0).0, [8, 4, 9]);
    }
}
