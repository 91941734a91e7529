//! The OME-TIFF writer: one 8-bit grey IFD per channel per frame (R, G, B of frame 0, then
//! of frame 1, ...), uncompressed, each with the scale as XResolution/YResolution (pixels
//! per centimetre); the first IFD's ImageDescription holds the OME-XML ([`super::ome_xml`]).
//! A file past what a classic TIFF's 32-bit offsets reach is written as BigTIFF.

use super::ome_xml;
use super::{partial_path, put_in_place, ExportError, Source};
use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Seek, Write};
use std::path::Path;
use tiff::encoder::colortype::Gray8;
use tiff::encoder::{Rational, TiffEncoder, TiffKind};
use tiff::tags::{ResolutionUnit, Tag};

/// Classic TIFF up to this many bytes of pixels (offsets are 32-bit; leave room for the
/// OME-XML and the IFDs).
const CLASSIC_MAX_PIXEL_BYTES: u64 = 3 << 30;

/// Write `src` as an OME-TIFF at `out` (via a hidden temporary renamed into place).
pub fn write(src: &Source, out: &Path) -> Result<(), ExportError> {
    let tmp = partial_path(out);
    // A temporary left by an export that was killed: ours to remove (a symlink too: it is
    // unlinked, never followed).
    let _ = std::fs::remove_file(&tmp);
    let file = OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&tmp)
        .map_err(|e| ExportError::output(out, format!("cannot create {}: {e}", tmp.display())))?;
    let written = write_file(src, file, out);
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written?;
    put_in_place(&tmp, out)
}

fn write_file(src: &Source, file: File, out: &Path) -> Result<(), ExportError> {
    let (w, h) = src.frame_size;
    let pixel_bytes = 3 * src.planes.len() as u64 * u64::from(w) * u64::from(h);
    let mut buf = BufWriter::with_capacity(1 << 20, file);
    let tiff_err = |e: tiff::TiffError| ExportError::output(out, format!("TIFF: {e}"));
    if pixel_bytes > CLASSIC_MAX_PIXEL_BYTES {
        frames(src, TiffEncoder::new_big(&mut buf).map_err(tiff_err)?, out)?;
    } else {
        frames(src, TiffEncoder::new(&mut buf).map_err(tiff_err)?, out)?;
    }
    let file = buf
        .into_inner()
        .map_err(|e| ExportError::output(out, e.error()))?;
    file.sync_all().map_err(|e| ExportError::output(out, e))
}

/// The resolution tags' pixels per centimetre for a scale in µm/px, as a fraction.
pub fn pixels_per_cm(scale_um_per_px: f64) -> Rational {
    let per_cm = 1e4 / scale_um_per_px;
    let mut d: u32 = 1_000_000;
    while d > 1 && per_cm * f64::from(d) > f64::from(u32::MAX) {
        d /= 10;
    }
    let n = (per_cm * f64::from(d))
        .round()
        .clamp(1.0, f64::from(u32::MAX)) as u32;
    Rational { n, d }
}

fn frames<W: Write + Seek, K: TiffKind>(
    src: &Source,
    mut enc: TiffEncoder<W, K>,
    out: &Path,
) -> Result<(), ExportError> {
    let (w, h) = src.frame_size;
    let manifest = serde_json::to_string(&src.session.manifest)
        .map_err(|e| ExportError::output(out, format!("manifest: {e}")))?;
    let description = format!(
        "rigd session {}: job {}, {} frames, state {}",
        src.name(),
        src.session.manifest.job_id,
        src.planes.len(),
        serde_json::to_value(src.session.manifest.state)
            .ok()
            .and_then(|v| v.as_str().map(str::to_string))
            .unwrap_or_default(),
    );
    let xml = ome_xml::document(&ome_xml::Image {
        name: src.name(),
        size_x: w,
        size_y: h,
        scale_um_per_px: src.scale_um_per_px(),
        planes: &src.planes,
        manifest_json: &manifest,
        description: &description,
    });
    let software = format!("rigd {}", env!("CARGO_PKG_VERSION"));
    let resolution = pixels_per_cm(src.scale_um_per_px());
    let n = (w * h) as usize;
    src.for_each_frame(|t, planar| {
        for c in 0..3 {
            let at = |e: tiff::TiffError| {
                ExportError::output(
                    out,
                    format!("TIFF: frame {} channel {c}: {e}", src.planes.index[t]),
                )
            };
            let mut img = enc.new_image::<Gray8>(w, h).map_err(at)?;
            if t == 0 && c == 0 {
                img.encoder()
                    .write_tag(Tag::ImageDescription, xml.as_str())
                    .map_err(at)?;
            }
            img.encoder()
                .write_tag(Tag::Software, software.as_str())
                .map_err(at)?;
            img.resolution(ResolutionUnit::Centimeter, resolution.clone());
            img.write_data(&planar[c * n..(c + 1) * n]).map_err(at)?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resolution_fractions_keep_the_scale() {
        // 774 µm/px: 12.919... px/cm.
        let r = pixels_per_cm(774.0);
        assert!(
            (f64::from(r.n) / f64::from(r.d) - 1e4 / 774.0).abs() < 1e-6,
            "{}/{}",
            r.n,
            r.d
        );
        let r = pixels_per_cm(0.05);
        assert!(
            (f64::from(r.n) / f64::from(r.d) - 2e5).abs() < 1e-3,
            "{}/{}",
            r.n,
            r.d
        );
    }
}
