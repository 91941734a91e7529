//! Camera pixel formats to 8-bit RGB: packed YUYV 4:2:2, Motion-JPEG, and packed RGB24 (RGB3).
//!
//! Independent of V4L2 (no feature needed) so the conversions are tested on fixture buffers in
//! every build. YUYV is decoded with the BT.601 limited-range matrix, which is what V4L2 means
//! by the default colourspace of a SD/HD webcam's YUYV (SMPTE 170M, Y in 16..235).

use image::RgbImage;
use serde::{Deserialize, Serialize};

/// A capture format rigd can convert. The names are V4L2's fourccs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum PixelFormat {
    /// Packed 4:2:2: Y0 U Y1 V for each pair of pixels.
    #[serde(rename = "YUYV")]
    Yuyv,
    /// Motion-JPEG: every buffer is a JPEG image.
    #[serde(rename = "MJPG")]
    Mjpg,
    /// Packed 8-bit R, G, B.
    #[serde(rename = "RGB3")]
    Rgb3,
}

impl PixelFormat {
    pub const ALL: [PixelFormat; 3] = [PixelFormat::Yuyv, PixelFormat::Mjpg, PixelFormat::Rgb3];

    pub fn fourcc(self) -> [u8; 4] {
        match self {
            PixelFormat::Yuyv => *b"YUYV",
            PixelFormat::Mjpg => *b"MJPG",
            PixelFormat::Rgb3 => *b"RGB3",
        }
    }

    pub fn from_fourcc(code: [u8; 4]) -> Option<PixelFormat> {
        PixelFormat::ALL.into_iter().find(|f| f.fourcc() == code)
    }

    /// Minimum bytes per line for an uncompressed format (`None` for MJPG).
    pub fn min_stride(self, width: u32) -> Option<usize> {
        match self {
            PixelFormat::Yuyv => Some(width as usize * 2),
            PixelFormat::Rgb3 => Some(width as usize * 3),
            PixelFormat::Mjpg => None,
        }
    }
}

impl std::fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(std::str::from_utf8(&self.fourcc()).unwrap_or("????"))
    }
}

impl std::str::FromStr for PixelFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let up = s.trim().to_ascii_uppercase();
        let code: [u8; 4] = up
            .as_bytes()
            .try_into()
            .map_err(|_| format!("unknown pixel format {s:?} (expected YUYV, MJPG or RGB3)"))?;
        PixelFormat::from_fourcc(code)
            .ok_or_else(|| format!("unknown pixel format {s:?} (expected YUYV, MJPG or RGB3)"))
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PixfmtError {
    #[error("{format} buffer of {got} bytes is too short for {width}x{height} with {stride} bytes per line (need {need})")]
    Short {
        format: PixelFormat,
        width: u32,
        height: u32,
        stride: usize,
        got: usize,
        need: usize,
    },
    #[error("{format}: {stride} bytes per line is less than the {min} a {width}-pixel row needs")]
    Stride {
        format: PixelFormat,
        width: u32,
        stride: usize,
        min: usize,
    },
    #[error("YUYV needs an even width, got {0}")]
    OddWidth(u32),
    #[error("MJPG frame does not decode: {0}")]
    Jpeg(String),
    #[error("MJPG frame is {got_w}x{got_h}, the negotiated size is {width}x{height}")]
    JpegSize {
        got_w: u32,
        got_h: u32,
        width: u32,
        height: u32,
    },
}

/// Convert one buffer (already sliced to the driver's `bytesused`) to RGB.
/// `stride` is the driver's bytes per line (ignored for MJPG); 0 means tightly packed.
pub fn to_rgb(
    format: PixelFormat,
    data: &[u8],
    width: u32,
    height: u32,
    stride: usize,
) -> Result<RgbImage, PixfmtError> {
    match format {
        PixelFormat::Yuyv => yuyv_to_rgb(data, width, height, stride),
        PixelFormat::Rgb3 => rgb3_to_rgb(data, width, height, stride),
        PixelFormat::Mjpg => {
            let img = mjpg_to_rgb(data)?;
            if img.dimensions() != (width, height) {
                return Err(PixfmtError::JpegSize {
                    got_w: img.width(),
                    got_h: img.height(),
                    width,
                    height,
                });
            }
            Ok(img)
        }
    }
}

fn check_len(
    format: PixelFormat,
    data: &[u8],
    width: u32,
    height: u32,
    stride: usize,
) -> Result<usize, PixfmtError> {
    let min = format.min_stride(width).unwrap_or(0);
    let stride = if stride == 0 { min } else { stride };
    if stride < min {
        return Err(PixfmtError::Stride {
            format,
            width,
            stride,
            min,
        });
    }
    // The last line need not be padded out to the full stride.
    let need = if height == 0 {
        0
    } else {
        stride * (height as usize - 1) + min
    };
    if data.len() < need {
        return Err(PixfmtError::Short {
            format,
            width,
            height,
            stride,
            got: data.len(),
            need,
        });
    }
    Ok(stride)
}

/// BT.601 limited range Y'CbCr to R'G'B' (ITU-R BT.601, 8-bit, Y in 16..235, C in 16..240).
#[inline]
pub fn ycbcr_to_rgb(y: u8, cb: u8, cr: u8) -> [u8; 3] {
    let y = 1.164_383_6 * (f32::from(y) - 16.0);
    let cb = f32::from(cb) - 128.0;
    let cr = f32::from(cr) - 128.0;
    let r = y + 1.596_026_8 * cr;
    let g = y - 0.391_762_3 * cb - 0.812_967_6 * cr;
    let b = y + 2.017_232_1 * cb;
    let q = |v: f32| v.round().clamp(0.0, 255.0) as u8;
    [q(r), q(g), q(b)]
}

/// Packed YUYV (Y0 Cb Y1 Cr per pixel pair) to RGB.
pub fn yuyv_to_rgb(
    data: &[u8],
    width: u32,
    height: u32,
    stride: usize,
) -> Result<RgbImage, PixfmtError> {
    if width & 1 != 0 {
        return Err(PixfmtError::OddWidth(width));
    }
    let stride = check_len(PixelFormat::Yuyv, data, width, height, stride)?;
    let mut out = RgbImage::new(width, height);
    let row_bytes = width as usize * 3;
    for (v, row) in out.chunks_exact_mut(row_bytes).enumerate() {
        let src = &data[v * stride..v * stride + width as usize * 2];
        for (quad, px) in src.chunks_exact(4).zip(row.chunks_exact_mut(6)) {
            let (y0, cb, y1, cr) = (quad[0], quad[1], quad[2], quad[3]);
            px[..3].copy_from_slice(&ycbcr_to_rgb(y0, cb, cr));
            px[3..].copy_from_slice(&ycbcr_to_rgb(y1, cb, cr));
        }
    }
    Ok(out)
}

/// Packed RGB24 (V4L2 `RGB3`: R, G, B bytes) to an image, dropping any line padding.
pub fn rgb3_to_rgb(
    data: &[u8],
    width: u32,
    height: u32,
    stride: usize,
) -> Result<RgbImage, PixfmtError> {
    let stride = check_len(PixelFormat::Rgb3, data, width, height, stride)?;
    let row_bytes = width as usize * 3;
    let mut buf = Vec::with_capacity(row_bytes * height as usize);
    for v in 0..height as usize {
        buf.extend_from_slice(&data[v * stride..v * stride + row_bytes]);
    }
    Ok(RgbImage::from_raw(width, height, buf).expect("buffer sized to width*height*3"))
}

/// One Motion-JPEG buffer to RGB.
pub fn mjpg_to_rgb(data: &[u8]) -> Result<RgbImage, PixfmtError> {
    // Some UVC cameras pad the buffer after the JPEG's end-of-image marker: cut there.
    let end = data
        .windows(2)
        .rposition(|w| w == [0xFF, 0xD9])
        .map(|i| i + 2)
        .unwrap_or(data.len());
    let img = image::load_from_memory_with_format(&data[..end], image::ImageFormat::Jpeg)
        .map_err(|e| PixfmtError::Jpeg(e.to_string()))?;
    Ok(img.to_rgb8())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The fixtures: an 8x4 pattern of colours (pixel pairs share a colour, as 4:2:2 chroma
    /// does), its YUYV encoding by the BT.601 forward formulas, and a 16x16 JPEG.
    /// Regenerate with `cargo test --lib hw::pixfmt -- --ignored write_fixtures`.
    const PATTERN_RGB: &[u8] = include_bytes!("../../tests/fixtures/pattern_8x4.rgb");
    const PATTERN_YUYV: &[u8] = include_bytes!("../../tests/fixtures/pattern_8x4.yuyv");
    const PATTERN_JPG: &[u8] = include_bytes!("../../tests/fixtures/pattern_16x16.jpg");

    /// The 8x4 pattern: primaries, secondaries, greys, and a ramp.
    fn pattern_8x4() -> Vec<u8> {
        let pairs: [[u8; 3]; 16] = [
            [255, 0, 0],
            [0, 255, 0],
            [0, 0, 255],
            [255, 255, 255],
            [0, 0, 0],
            [255, 255, 0],
            [0, 255, 255],
            [255, 0, 255],
            [128, 128, 128],
            [200, 40, 40],
            [40, 200, 40],
            [40, 40, 200],
            [16, 32, 64],
            [64, 128, 192],
            [230, 120, 10],
            [90, 90, 90],
        ];
        pairs.iter().flat_map(|c| [*c, *c]).flatten().collect()
    }

    /// BT.601 limited-range forward transform (the encoder side, written out independently).
    fn rgb_to_ycbcr(c: [u8; 3]) -> [u8; 3] {
        let [r, g, b] = c.map(|v| f64::from(v) / 255.0);
        let y = 16.0 + 65.481 * r + 128.553 * g + 24.966 * b;
        let cb = 128.0 - 37.797 * r - 74.203 * g + 112.0 * b;
        let cr = 128.0 + 112.0 * r - 93.786 * g - 18.214 * b;
        [y, cb, cr].map(|v| v.round().clamp(0.0, 255.0) as u8)
    }

    fn pattern_yuyv(rgb: &[u8]) -> Vec<u8> {
        rgb.chunks_exact(6)
            .flat_map(|pair| {
                let a = rgb_to_ycbcr([pair[0], pair[1], pair[2]]);
                let b = rgb_to_ycbcr([pair[3], pair[4], pair[5]]);
                let cb = (u16::from(a[1]) + u16::from(b[1])).div_ceil(2) as u8;
                let cr = (u16::from(a[2]) + u16::from(b[2])).div_ceil(2) as u8;
                [a[0], cb, b[0], cr]
            })
            .collect()
    }

    fn pattern_16x16() -> RgbImage {
        // Smooth gradients and a flat block: JPEG keeps them within a few DN.
        RgbImage::from_fn(16, 16, |x, y| {
            if (4..12).contains(&x) && (4..12).contains(&y) {
                image::Rgb([200, 30, 30])
            } else {
                image::Rgb([(x * 12) as u8 + 40, (y * 12) as u8 + 40, 128])
            }
        })
    }

    #[test]
    #[ignore = "writes tests/fixtures; run by hand to regenerate"]
    fn write_fixtures() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures");
        std::fs::create_dir_all(&dir).unwrap();
        let rgb = pattern_8x4();
        std::fs::write(dir.join("pattern_8x4.rgb"), &rgb).unwrap();
        std::fs::write(dir.join("pattern_8x4.yuyv"), pattern_yuyv(&rgb)).unwrap();
        let mut jpg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpg, 95)
            .encode_image(&pattern_16x16())
            .unwrap();
        std::fs::write(dir.join("pattern_16x16.jpg"), jpg).unwrap();
    }

    fn max_diff(a: &[u8], b: &[u8]) -> u8 {
        assert_eq!(a.len(), b.len());
        a.iter().zip(b).map(|(x, y)| x.abs_diff(*y)).max().unwrap()
    }

    #[test]
    fn fixtures_match_the_pattern() {
        assert_eq!(PATTERN_RGB, pattern_8x4().as_slice());
        assert_eq!(PATTERN_YUYV.len(), 8 * 4 * 2);
    }

    #[test]
    fn yuyv_fixture_decodes_to_the_pattern() {
        let img = yuyv_to_rgb(PATTERN_YUYV, 8, 4, 0).unwrap();
        // 8-bit Y'CbCr quantisation costs up to ~2 DN per channel on the round trip.
        assert!(max_diff(img.as_raw(), PATTERN_RGB) <= 2);
        assert!(max_diff(&img.get_pixel(0, 0).0, &[255, 0, 0]) <= 1);
        assert_eq!(img.get_pixel(6, 0).0, [255, 255, 255]);
        assert_eq!(img.get_pixel(0, 1).0, [0, 0, 0]);
    }

    #[test]
    fn yuyv_reference_values() {
        assert_eq!(ycbcr_to_rgb(235, 128, 128), [255, 255, 255]);
        assert_eq!(ycbcr_to_rgb(16, 128, 128), [0, 0, 0]);
        assert_eq!(ycbcr_to_rgb(126, 128, 128), [128, 128, 128]);
        // Full red is Y=81.5, Cb=90.2, Cr=240.0: 8-bit rounding leaves it 1 DN short.
        assert_eq!(ycbcr_to_rgb(81, 90, 240), [254, 0, 0]);
        // Full blue: Y=41, Cb=240, Cr=110.
        assert!(max_diff(&ycbcr_to_rgb(41, 240, 110), &[0, 0, 255]) <= 1);
    }

    #[test]
    fn yuyv_honours_stride_and_pixel_pairs() {
        // 2x2 with 2 bytes of padding per line; the chroma of a pair applies to both pixels.
        let data = [
            235, 128, 16, 128, 0xAA, 0xAA, //
            81, 90, 81, 240, 0xAA, 0xAA,
        ];
        let img = yuyv_to_rgb(&data, 2, 2, 6).unwrap();
        assert_eq!(img.get_pixel(0, 0).0, [255, 255, 255]);
        assert_eq!(img.get_pixel(1, 0).0, [0, 0, 0]);
        assert_eq!(img.get_pixel(0, 1).0, [254, 0, 0]);
        assert_eq!(img.get_pixel(1, 1).0, [254, 0, 0]);
    }

    #[test]
    fn short_and_odd_buffers_are_errors() {
        let e = yuyv_to_rgb(&PATTERN_YUYV[..60], 8, 4, 0).unwrap_err();
        assert_eq!(
            e,
            PixfmtError::Short {
                format: PixelFormat::Yuyv,
                width: 8,
                height: 4,
                stride: 16,
                got: 60,
                need: 64
            }
        );
        assert_eq!(
            yuyv_to_rgb(PATTERN_YUYV, 7, 4, 0).unwrap_err(),
            PixfmtError::OddWidth(7)
        );
        assert!(matches!(
            rgb3_to_rgb(PATTERN_RGB, 8, 4, 10).unwrap_err(),
            PixfmtError::Stride { min: 24, .. }
        ));
    }

    #[test]
    fn rgb3_copies_and_strips_padding() {
        let img = rgb3_to_rgb(PATTERN_RGB, 8, 4, 0).unwrap();
        assert_eq!(img.as_raw().as_slice(), PATTERN_RGB);
        // Same data with 4 padding bytes per line.
        let padded: Vec<u8> = PATTERN_RGB
            .chunks_exact(24)
            .flat_map(|r| r.iter().copied().chain([9, 9, 9, 9]))
            .collect();
        let img = to_rgb(PixelFormat::Rgb3, &padded, 8, 4, 28).unwrap();
        assert_eq!(img.as_raw().as_slice(), PATTERN_RGB);
    }

    #[test]
    fn mjpg_fixture_decodes() {
        let img = to_rgb(PixelFormat::Mjpg, PATTERN_JPG, 16, 16, 0).unwrap();
        let want = pattern_16x16();
        // Quality 95 with 4:2:0 chroma: the flat red block's interior is exact to a few DN.
        for (x, y) in [(6, 6), (8, 8), (9, 6)] {
            let d = max_diff(&img.get_pixel(x, y).0, &want.get_pixel(x, y).0);
            assert!(d <= 6, "pixel ({x},{y}) off by {d}");
        }
        let mean_err = img
            .as_raw()
            .iter()
            .zip(want.as_raw())
            .map(|(a, b)| f64::from(a.abs_diff(*b)))
            .sum::<f64>()
            / img.as_raw().len() as f64;
        assert!(mean_err < 6.0, "mean error {mean_err}");
        // Padding after the end-of-image marker (as some UVC cameras send) is ignored.
        let mut padded = PATTERN_JPG.to_vec();
        padded.extend_from_slice(&[0; 64]);
        assert_eq!(mjpg_to_rgb(&padded).unwrap(), img);
    }

    #[test]
    fn mjpg_garbage_and_wrong_size_are_errors() {
        assert!(matches!(
            mjpg_to_rgb(&[0xFF, 0xD8, 1, 2, 3]),
            Err(PixfmtError::Jpeg(_))
        ));
        assert!(matches!(
            to_rgb(PixelFormat::Mjpg, PATTERN_JPG, 32, 16, 0),
            Err(PixfmtError::JpegSize { got_w: 16, .. })
        ));
    }

    #[test]
    fn format_names_parse() {
        assert_eq!("yuyv".parse::<PixelFormat>(), Ok(PixelFormat::Yuyv));
        assert_eq!("MJPG".parse::<PixelFormat>(), Ok(PixelFormat::Mjpg));
        assert!("H264".parse::<PixelFormat>().is_err());
        assert_eq!(PixelFormat::Rgb3.to_string(), "RGB3");
    }
}
