//! What rigd accepts from files it did not just write and from the wire: sizes of the files
//! it reads (sessions, folders, calibration records), image dimensions, the range of every
//! number it parses, and names that become file names. One place, so the readers agree.

/// A session's `manifest.json`, a calibration record, `.next-job-id`: small documents.
pub const MAX_DOCUMENT_BYTES: u64 = 16 << 20;
/// A session's or a folder's `steps.csv` (a million frames is ~100 MB: far beyond a job).
pub const MAX_STEPS_BYTES: u64 = 64 << 20;
/// A session's `interferometer.csv` (hours of 1 kHz samples).
pub const MAX_LOG_BYTES: u64 = 512 << 20;
/// One frame's PNG.
pub const MAX_FRAME_BYTES: u64 = 64 << 20;
/// A frame's longest side, px.
pub const MAX_FRAME_SIDE_PX: u32 = 16_384;
/// A frame's pixels (width x height): 4096 x 4096, 48 MB as 8-bit RGB.
pub const MAX_FRAME_PIXELS: u64 = 4096 * 4096;
/// The latest time rigd reads from a file, s since the epoch (the year 2286).
pub const MAX_UNIX_S: f64 = 1e10;
/// The largest position magnitude rigd reads, µm (1 km: beyond any stage).
pub const MAX_POSITION_UM: f64 = 1e9;
/// The longest step phase (move, settle, grab) rigd reads, ms (11.6 days).
pub const MAX_PHASE_MS: f64 = 1e9;

/// `value` if it lies in `lo..=hi` (NaN never does), else why not, naming `what`.
pub fn in_range(what: &str, value: f64, lo: f64, hi: f64) -> Result<f64, String> {
    if (lo..=hi).contains(&value) {
        Ok(value)
    } else {
        let (v, lo, hi) = (short(value), short(lo), short(hi));
        Err(format!("{what} {v} is outside {lo}..={hi}"))
    }
}

/// A number as a message shows it: `1e300`, not its 301 digits.
pub fn short(v: f64) -> String {
    let a = v.abs();
    if a != 0.0 && a.is_finite() && !(1e-4..1e15).contains(&a) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// `name` if it is one plain path component (not empty, `.`, `..`, no `/` or NUL, not
/// hidden): safe to join below a folder. `what` names it in the error.
pub fn one_component<'a>(what: &str, name: &'a str) -> Result<&'a str, String> {
    let plain = !name.is_empty()
        && !name.starts_with('.')
        && !name.contains(['/', '\\', '\0'])
        && name.len() <= 255;
    if plain {
        Ok(name)
    } else {
        Err(format!(
            "{what} {name:?} is not a plain file name (one path component, no `/`, not \
             starting with `.`, at most 255 bytes)"
        ))
    }
}

/// `text` cut to its first `max_chars` characters (saying how long it was): what an error
/// quotes of something read from a file.
pub fn cut(text: &str, max_chars: usize) -> String {
    let n = text.chars().count();
    if n <= max_chars {
        return text.to_string();
    }
    let start: String = text.chars().take(max_chars).collect();
    format!("{start}… ({n} characters)")
}

/// A frame's dimensions, if within [`MAX_FRAME_SIDE_PX`] and [`MAX_FRAME_PIXELS`].
pub fn frame_size(width: u32, height: u32) -> Result<(u32, u32), String> {
    let pixels = width as u64 * height as u64;
    if width == 0 || height == 0 || width.max(height) > MAX_FRAME_SIDE_PX {
        return Err(format!(
            "{width}x{height} px: each side must be 1..={MAX_FRAME_SIDE_PX} px"
        ));
    }
    if pixels > MAX_FRAME_PIXELS {
        return Err(format!(
            "{width}x{height} px: {pixels} pixels, over the {MAX_FRAME_PIXELS}-pixel limit"
        ));
    }
    Ok((width, height))
}

/// The `image` crate's limits for a frame of at most [`frame_size`]'s dimensions.
pub fn image_limits() -> image::Limits {
    let mut l = image::Limits::default();
    l.max_image_width = Some(MAX_FRAME_SIDE_PX);
    l.max_image_height = Some(MAX_FRAME_SIDE_PX);
    // 16-bit RGBA at the pixel limit, with room for the decoder's own buffers.
    l.max_alloc = Some(MAX_FRAME_PIXELS * 8 + (16 << 20));
    l
}

/// Decode a PNG frame as 8-bit RGB within [`frame_size`]'s limits; `expected`: the size
/// every frame of its run must have (the first frame's, the rig's).
pub fn decode_frame(bytes: &[u8], expected: Option<(u32, u32)>) -> Result<image::RgbImage, String> {
    let mut r =
        image::ImageReader::with_format(std::io::Cursor::new(bytes), image::ImageFormat::Png);
    r.limits(image_limits());
    let (w, h) = r
        .into_dimensions()
        .map_err(|e| format!("not a readable PNG: {e}"))?;
    frame_size(w, h)?;
    if let Some((ew, eh)) = expected.filter(|&e| e != (w, h)) {
        return Err(format!(
            "size {w}x{h} px differs from the run's frames', {ew}x{eh} px"
        ));
    }
    let mut r =
        image::ImageReader::with_format(std::io::Cursor::new(bytes), image::ImageFormat::Png);
    r.limits(image_limits());
    let img = r.decode().map_err(|e| format!("not a readable PNG: {e}"))?;
    Ok(img.into_rgb8())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_outside_their_range_are_named() {
        assert_eq!(in_range("x_um", 0.0, -1.0, 1.0), Ok(0.0));
        assert_eq!(in_range("x_um", -0.0, 0.0, 1.0), Ok(-0.0));
        for v in [
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            1e308,
            -1e308,
            1.0000001,
        ] {
            let e = in_range("x_um", v, -1.0, 1.0).unwrap_err();
            assert!(e.starts_with("x_um ") && e.len() < 60, "{e}");
        }
        let e = in_range("t_unix_s", 1e300, 0.0, 1e10).unwrap_err();
        assert_eq!(e, "t_unix_s 1e300 is outside 0..=10000000000");
    }

    #[test]
    fn names_must_be_one_plain_component() {
        for ok in ["cal-20261201", "a b", "Ω"] {
            assert_eq!(one_component("id", ok), Ok(ok));
        }
        let long = "x".repeat(256);
        for bad in [
            "",
            ".",
            "..",
            "q/../../x",
            "/abs",
            ".hidden",
            "a\0b",
            "a\\b",
            &long,
        ] {
            let e = one_component("id", bad).unwrap_err();
            assert!(e.contains("is not a plain file name"), "{bad:?}: {e}");
        }
    }

    /// A small PNG declaring `w` x `h` 8-bit RGB: its signature, IHDR, a token IDAT and IEND
    /// (the pixels are never there: a decoder must refuse it from the header).
    fn declared_png(w: u32, h: u32) -> Vec<u8> {
        let mut v = b"\x89PNG\r\n\x1a\n".to_vec();
        let mut chunk = |kind: &[u8], data: &[u8]| {
            v.extend_from_slice(&(data.len() as u32).to_be_bytes());
            let start = v.len();
            v.extend_from_slice(kind);
            v.extend_from_slice(data);
            let crc = crc32fast::hash(&v[start..]);
            v.extend_from_slice(&crc.to_be_bytes());
        };
        let mut ihdr = Vec::new();
        ihdr.extend_from_slice(&w.to_be_bytes());
        ihdr.extend_from_slice(&h.to_be_bytes());
        ihdr.extend_from_slice(&[8, 2, 0, 0, 0]);
        chunk(b"IHDR", &ihdr);
        chunk(b"IDAT", &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01]);
        chunk(b"IEND", &[]);
        v
    }

    #[test]
    fn frames_beyond_the_dimension_limits_are_refused_before_decoding() {
        assert_eq!(frame_size(1280, 720), Ok((1280, 720)));
        assert!(frame_size(30_000, 30_000)
            .unwrap_err()
            .contains("1..=16384"));
        assert!(frame_size(16_000, 16_000)
            .unwrap_err()
            .contains("pixel limit"));
        assert!(frame_size(0, 5).is_err());
        // A small PNG declaring 30000 x 30000: refused from its header, nothing allocated.
        let e = decode_frame(&declared_png(30_000, 30_000), None).unwrap_err();
        assert!(e.contains("30000x30000") || e.contains("limit"), "{e}");
        let img = image::RgbImage::new(4, 3);
        let mut ok = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut ok), image::ImageFormat::Png)
            .unwrap();
        assert_eq!(
            decode_frame(&ok, Some((4, 3))).unwrap().dimensions(),
            (4, 3)
        );
        let e = decode_frame(&ok, Some((5, 3))).unwrap_err();
        assert!(e.contains("size 4x3 px differs"), "{e}");
    }
}
