//! A session frame as PNG carrying its own metadata: `pHYs` (the scene's pixels per metre,
//! from the rig's µm/px scale) and `tEXt` chunks with where and when the frame was taken
//! (docs/sessions.md), so a frame copied out of its session still says what it shows.
//!
//! Encoded with the `png` crate directly: fast deflate (`fdeflate`, as `image`'s PNG encoder
//! uses) and every row filtered `Up`, the filter cheapest to undo. On the simulated rig's
//! noisy frames `Up` makes files ~5 % larger than an adaptive choice per row (mostly
//! `Average`) and a frame 22 % faster to decode (2.66 against 3.42 ms for 1280x720 here:
//! undoing `Average` is a chain along each row, undoing `Up` one vector add), and 25 %
//! faster to write; a session is written once and read by every reprocessing
//! (docs/performance.md, "Frames measured where they are decoded").

use crate::session::StepRow;
use image::RgbImage;

/// The `tEXt` keywords a frame carries, in the order written.
pub const TEXT_KEYS: [&str; 9] = [
    "session",
    "index",
    "position_um",
    "axis_um",
    "interferometer_um",
    "piezo_commanded_um",
    "piezo_um",
    "t_unix_s",
    "scale_um_per_px",
];

/// `pHYs` pixels per metre of the scene for a scale in µm/px; none when the scale gives no
/// whole number of pixels per metre that fits the chunk (not finite, not positive, too big).
pub fn pixels_per_metre(scale_um_per_px: f64) -> Option<u32> {
    let ppm = (1e6 / scale_um_per_px).round();
    (ppm.is_finite() && ppm >= 1.0 && ppm <= f64::from(u32::MAX)).then_some(ppm as u32)
}

/// The text chunks of frame `row` of `session`: numbers in the shortest form that reads
/// back to the same f64 (as steps.csv has them); readings the frame has not are left out.
pub fn text_chunks(session: &str, row: &StepRow, scale_um_per_px: f64) -> Vec<(String, String)> {
    let values = [
        Some(session.to_string()),
        Some(row.index.to_string()),
        Some(row.position_um.to_string()),
        Some(row.axis_um.to_string()),
        row.interferometer_um.map(|v| v.to_string()),
        row.piezo_commanded_um.map(|v| v.to_string()),
        row.piezo_um.map(|v| v.to_string()),
        Some(row.t_unix_s.to_string()),
        Some(scale_um_per_px.to_string()),
    ];
    TEXT_KEYS
        .iter()
        .zip(values)
        .filter_map(|(k, v)| Some((k.to_string(), v?)))
        .collect()
}

/// `image` as an 8-bit RGB PNG with `pHYs` for `scale_um_per_px` and `text` as `tEXt`.
pub fn encode(
    image: &RgbImage,
    scale_um_per_px: f64,
    text: Vec<(String, String)>,
) -> Result<Vec<u8>, png::EncodingError> {
    let mut out = Vec::with_capacity(image.as_raw().len() / 2);
    let mut enc = png::Encoder::new(&mut out, image.width(), image.height());
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    enc.set_compression(png::Compression::Fast);
    enc.set_filter(png::Filter::Up);
    if let Some(ppm) = pixels_per_metre(scale_um_per_px) {
        enc.set_pixel_dims(Some(png::PixelDimensions {
            xppu: ppm,
            yppu: ppm,
            unit: png::Unit::Meter,
        }));
    }
    for (k, v) in text {
        enc.add_text_chunk(k, v)?;
    }
    let mut w = enc.write_header()?;
    w.write_image_data(image.as_raw())?;
    w.finish()?;
    Ok(out)
}

/// The metadata a frame PNG carries: its `pHYs` pixels per metre (if any) and text chunks.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameMeta {
    pub pixels_per_metre: Option<(u32, u32)>,
    pub text: Vec<(String, String)>,
}

impl FrameMeta {
    /// The text chunk `key`, if the frame has it.
    pub fn get(&self, key: &str) -> Option<&str> {
        self.text
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
}

/// Read a frame PNG's metadata (header chunks only: the pixels are not inflated).
pub fn read_meta(bytes: &[u8]) -> Result<FrameMeta, png::DecodingError> {
    let reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info()?;
    let info = reader.info();
    let pixels_per_metre = info
        .pixel_dims
        .filter(|d| d.unit == png::Unit::Meter)
        .map(|d| (d.xppu, d.yppu));
    let text = info
        .uncompressed_latin1_text
        .iter()
        .map(|t| (t.keyword.clone(), t.text.clone()))
        .collect();
    Ok(FrameMeta {
        pixels_per_metre,
        text,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row() -> StepRow {
        StepRow {
            index: 7,
            position_um: 1050.25,
            run: 0,
            case: "a".into(),
            repeat: 0,
            axis_um: 1050.2501,
            interferometer_um: Some(-3.125),
            t_unix_s: 1_795_000_000.123_456,
            sequence: 9,
            move_ms: 1.0,
            settle_ms: 2.0,
            grab_ms: 3.0,
            piezo_commanded_um: None,
            piezo_um: None,
        }
    }

    #[test]
    fn a_frame_reads_back_its_pixels_scale_and_text() {
        let img = RgbImage::from_fn(5, 3, |x, y| image::Rgb([x as u8 * 40, y as u8 * 70, 9]));
        let png = encode(&img, 2.5, text_chunks("S-job1", &row(), 2.5)).unwrap();
        let back = image::load_from_memory_with_format(&png, image::ImageFormat::Png)
            .unwrap()
            .into_rgb8();
        assert_eq!(back, img);
        let meta = read_meta(&png).unwrap();
        // 2.5 µm/px is 400 000 px/m.
        assert_eq!(meta.pixels_per_metre, Some((400_000, 400_000)));
        assert_eq!(meta.get("session"), Some("S-job1"));
        assert_eq!(meta.get("index"), Some("7"));
        assert_eq!(meta.get("position_um").unwrap().parse::<f64>(), Ok(1050.25));
        assert_eq!(meta.get("axis_um").unwrap().parse::<f64>(), Ok(1050.2501));
        assert_eq!(meta.get("interferometer_um"), Some("-3.125"));
        assert_eq!(
            meta.get("t_unix_s").unwrap().parse::<f64>(),
            Ok(1_795_000_000.123_456)
        );
        // No piezo on this plan: no piezo chunks.
        assert_eq!(meta.get("piezo_um"), None);
        assert_eq!(meta.get("scale_um_per_px"), Some("2.5"));
    }

    #[test]
    fn scales_without_a_whole_pixel_per_metre_write_no_phys() {
        assert_eq!(pixels_per_metre(774.0), Some(1292));
        assert_eq!(pixels_per_metre(0.0), None);
        assert_eq!(pixels_per_metre(f64::NAN), None);
        assert_eq!(pixels_per_metre(-1.0), None);
        assert_eq!(pixels_per_metre(1e-9), None);
        let img = RgbImage::new(2, 2);
        let meta = read_meta(&encode(&img, f64::NAN, Vec::new()).unwrap()).unwrap();
        assert_eq!(meta.pixels_per_metre, None);
    }
}
