//! The OME-XML an OME-TIFF carries in its first IFD's ImageDescription (OME 2016-06 schema):
//! one Image of `SizeT` frames × 3 channels (R, G, B), `DimensionOrder="XYCZT"` (so IFD
//! `3t + c` is channel c of frame t), `PhysicalSizeX/Y` in µm, and a Plane per IFD with its
//! `DeltaT` (s, from the first frame) and `PositionX` (the commanded position on the job's
//! stage, µm; `PositionY` the piezo's when the plan moves it besides). The session's
//! manifest and the whole per-plane table are in a MapAnnotation (`rigd-export/1`).
//!
//! TIFF's ASCII tags take 7-bit text only: every character past ASCII (µ, a case name's)
//! is written as an XML character reference, which XML readers decode.

use super::planes::Planes;
use std::fmt::Write;

/// OME's schema namespace and the MapAnnotation's.
pub const OME_NS: &str = "http://www.openmicroscopy.org/Schemas/OME/2016-06";
pub const ANNOTATION_NS: &str = "rigd-export/1";

/// What the document describes.
pub struct Image<'a> {
    pub name: &'a str,
    pub size_x: u32,
    pub size_y: u32,
    pub scale_um_per_px: f64,
    pub planes: &'a Planes,
    /// The session's manifest, as JSON.
    pub manifest_json: &'a str,
    pub description: &'a str,
}

/// `s` escaped for XML text and attribute values, in ASCII.
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for ch in s.chars() {
        match ch {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&apos;"),
            // Tabs and newlines in attributes would be normalised to spaces by a parser.
            c if !c.is_ascii() || (c.is_control() && c != '\n') => {
                let _ = write!(out, "&#{};", c as u32);
            }
            c => out.push(c),
        }
    }
    out
}

/// The micrometre as OME writes it (`µm`), ASCII-safe.
const UM: &str = "&#181;m";

/// A finite number as xsd:double (Rust's shortest round-trip form; never an exponent).
fn num(v: f64) -> Option<String> {
    v.is_finite().then(|| v.to_string())
}

/// A Unix time as RFC 3339 in UTC: OME's xsd:dateTime and NeXus' NX_DATE_TIME alike.
pub(super) fn utc_rfc3339(t_unix_s: f64) -> Option<String> {
    let ns = (t_unix_s * 1e9).round();
    if !ns.is_finite() {
        return None;
    }
    let t = time::OffsetDateTime::from_unix_timestamp_nanos(ns as i128).ok()?;
    t.format(&time::format_description::well_known::Rfc3339)
        .ok()
}

/// The OME-XML document.
pub fn document(img: &Image) -> String {
    let mut x = String::new();
    let _ = write!(
        x,
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<OME xmlns=\"{OME_NS}\" \
         xmlns:xsi=\"http://www.w3.org/2001/XMLSchema-instance\" \
         xsi:schemaLocation=\"{OME_NS} {OME_NS}/ome.xsd\" Creator=\"rigd {}\">\n",
        env!("CARGO_PKG_VERSION")
    );
    let _ = writeln!(x, "<Image ID=\"Image:0\" Name=\"{}\">", escape(img.name));
    if let Some(d) = img.planes.t_unix_s.first().and_then(|&t| utc_rfc3339(t)) {
        let _ = writeln!(x, "<AcquisitionDate>{d}</AcquisitionDate>");
    }
    let _ = writeln!(x, "<Description>{}</Description>", escape(img.description));
    pixels(&mut x, img);
    x.push_str("<AnnotationRef ID=\"Annotation:0\"/>\n</Image>\n");
    annotation(&mut x, img);
    x.push_str("</OME>\n");
    x
}

fn pixels(x: &mut String, img: &Image) {
    let n = img.planes.len();
    let s = num(img.scale_um_per_px).unwrap_or_else(|| "1".into());
    let _ = writeln!(
        x,
        "<Pixels ID=\"Pixels:0\" DimensionOrder=\"XYCZT\" Type=\"uint8\" SignificantBits=\"8\" \
         Interleaved=\"false\" BigEndian=\"false\" SizeX=\"{}\" SizeY=\"{}\" SizeC=\"3\" \
         SizeZ=\"1\" SizeT=\"{n}\" PhysicalSizeX=\"{s}\" PhysicalSizeXUnit=\"{UM}\" \
         PhysicalSizeY=\"{s}\" PhysicalSizeYUnit=\"{UM}\">",
        img.size_x, img.size_y
    );
    // Colours are RGBA as a signed 32-bit integer.
    for (c, (name, rgba)) in [
        ("R", 0xFF00_00FFu32),
        ("G", 0x00FF_00FF),
        ("B", 0x0000_FFFF),
    ]
    .into_iter()
    .enumerate()
    {
        let _ = writeln!(
            x,
            "<Channel ID=\"Channel:0:{c}\" Name=\"{name}\" SamplesPerPixel=\"1\" Color=\"{}\"/>",
            rgba as i32
        );
    }
    let _ = writeln!(x, "<TiffData IFD=\"0\" PlaneCount=\"{}\"/>", 3 * n);
    for t in 0..n {
        let mut at = String::new();
        if let Some(dt) = num(img.planes.delta_t_s(t)) {
            let _ = write!(at, " DeltaT=\"{dt}\" DeltaTUnit=\"s\"");
        }
        if let Some(p) = num(img.planes.position_um[t]) {
            let _ = write!(at, " PositionX=\"{p}\" PositionXUnit=\"{UM}\"");
        }
        if let Some(p) = img.planes.piezo_commanded_um[t].and_then(num) {
            let _ = write!(at, " PositionY=\"{p}\" PositionYUnit=\"{UM}\"");
        }
        for c in 0..3 {
            let _ = writeln!(x, "<Plane TheC=\"{c}\" TheZ=\"0\" TheT=\"{t}\"{at}/>");
        }
    }
    x.push_str("</Pixels>\n");
}

fn annotation(x: &mut String, img: &Image) {
    let scale = num(img.scale_um_per_px).unwrap_or_default();
    let entries = [
        ("session", img.name.to_string()),
        ("scale_um_per_px", scale),
        ("manifest", img.manifest_json.to_string()),
        ("planes", img.planes.csv()),
    ];
    let _ = writeln!(
        x,
        "<StructuredAnnotations>\n<MapAnnotation ID=\"Annotation:0\" Namespace=\"{ANNOTATION_NS}\">\n<Value>"
    );
    for (k, v) in entries {
        let _ = writeln!(x, "<M K=\"{k}\">{}</M>", escape(&v));
    }
    x.push_str("</Value>\n</MapAnnotation>\n</StructuredAnnotations>\n");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_is_escaped_into_ascii() {
        assert_eq!(
            escape("a<b & \"µ\"'"),
            "a&lt;b &amp; &quot;&#181;&quot;&apos;"
        );
        assert!(escape("x\ny\tz").contains("\n"));
        assert_eq!(escape("\t"), "&#9;");
    }

    #[test]
    fn acquisition_dates_are_utc() {
        assert_eq!(
            utc_rfc3339(1_795_000_000.5).as_deref(),
            Some("2026-11-18T11:06:40.5Z")
        );
    }
}
