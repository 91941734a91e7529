//! `rigctl export`: a session recorded by the daemon on the simulated rig (with its
//! interferometer) written as OME-TIFF and OME-Zarr, read back here with the `tiff` crate
//! and as Zarr v3 (the JSON documents and chunk files the spec defines): every pixel
//! equals the session's PNGs, the pixel size is the rig's scale in micrometres, the plane
//! positions and times are steps.csv's. The frames' own metadata (pHYs, tEXt), and exports
//! refused naming the session and frame at fault. (The reference Python readers, tifffile
//! and zarr/ome-zarr, read the same exports in tests/export_formats.sh.)

#![cfg(feature = "sim")] // the simulated rig (default feature)

mod support;

use image::RgbImage;
use rigd::export::{export, ExportError, Format};
use rigd::session::frame_png;
use rigd::session::Session;
use std::path::Path;
use support::daemon::{capture_job, record_small};
use tiff::decoder::{ifd::Value, Decoder, DecodingResult};
use tiff::tags::Tag;

const FRAMES: u32 = 5;

/// A finished 5-frame capture session on a small sim rig (64x40 frames, an interferometer),
/// copied out of the daemon's data root into `dir`.
fn record(dir: &Path) -> Session {
    record_small(dir, capture_job(100.0, FRAMES, 20))
}

fn frame(s: &Session, index: u32) -> RgbImage {
    image::open(s.frame_path(index)).unwrap().into_rgb8()
}

/// Channel `c` of `img`, row by row.
fn channel(img: &RgbImage, c: usize) -> Vec<u8> {
    img.as_raw().chunks_exact(3).map(|p| p[c]).collect()
}

/// The value of attribute `name` in the XML element text `elem`.
fn attr<'a>(elem: &'a str, name: &str) -> Option<&'a str> {
    let key = format!(" {name}=\"");
    let start = elem.find(&key)? + key.len();
    Some(&elem[start..start + elem[start..].find('"')?])
}

/// The first element `<tag ...>` of `xml` whose text contains `has`.
fn element<'a>(xml: &'a str, tag: &str, has: &str) -> &'a str {
    let open = format!("<{tag} ");
    xml.match_indices(&open)
        .map(|(i, _)| &xml[i..i + xml[i..].find('>').unwrap()])
        .find(|e| e.contains(has))
        .unwrap_or_else(|| panic!("no <{tag}> with {has:?}"))
}

#[test]
fn frames_carry_their_scale_position_time_and_session() {
    let dir = tempfile::tempdir().unwrap();
    let s = record(dir.path());
    let ppm = (1e6 / s.manifest.rig.scale_um_per_px).round() as u32;
    assert_eq!(s.steps.len(), FRAMES as usize);
    for r in &s.steps {
        let bytes = std::fs::read(s.frame_path(r.index)).unwrap();
        let meta = frame_png::read_meta(&bytes).unwrap();
        assert_eq!(meta.pixels_per_metre, Some((ppm, ppm)), "frame {}", r.index);
        let num = |k: &str| meta.get(k).unwrap().parse::<f64>().unwrap();
        assert_eq!(meta.get("session"), Some(s.manifest.name.as_str()));
        assert_eq!(meta.get("index"), Some(r.index.to_string().as_str()));
        assert_eq!(num("position_um"), r.position_um);
        assert_eq!(num("axis_um"), r.axis_um);
        assert_eq!(num("t_unix_s"), r.t_unix_s);
        let reading = r
            .interferometer_um
            .expect("the sim rig has an interferometer");
        assert_eq!(num("interferometer_um"), reading);
        assert_eq!(num("scale_um_per_px"), s.manifest.rig.scale_um_per_px);
    }
}

#[test]
fn ome_tiff_holds_every_pixel_with_its_scale_positions_and_times() {
    let dir = tempfile::tempdir().unwrap();
    let s = record(dir.path());
    let out = dir.path().join("out.ome.tif");
    let sum = export(&s.dir, Format::OmeTiff, &out).unwrap();
    assert_eq!((sum.frames, sum.frame_size), (FRAMES as usize, (64, 40)));
    let scale = s.manifest.rig.scale_um_per_px;

    let mut d = Decoder::new(std::fs::File::open(&out).unwrap()).unwrap();
    let xml = d
        .get_tag(Tag::ImageDescription)
        .unwrap()
        .into_string()
        .unwrap();
    assert!(
        xml.starts_with("<?xml") && xml.trim_end().ends_with("</OME>"),
        "{xml}"
    );
    let px = element(&xml, "Pixels", "SizeT");
    assert_eq!(attr(px, "DimensionOrder"), Some("XYCZT"));
    assert_eq!(attr(px, "SizeT"), Some(FRAMES.to_string().as_str()));
    assert_eq!(
        (attr(px, "SizeC"), attr(px, "SizeX"), attr(px, "SizeY")),
        (Some("3"), Some("64"), Some("40"))
    );
    assert_eq!(attr(px, "PhysicalSizeX").unwrap().parse::<f64>(), Ok(scale));
    assert_eq!(attr(px, "PhysicalSizeY").unwrap().parse::<f64>(), Ok(scale));
    assert_eq!(attr(px, "PhysicalSizeXUnit"), Some("&#181;m"), "µm");
    for (c, name) in ["R", "G", "B"].iter().enumerate() {
        let ch = element(&xml, "Channel", &format!("Channel:0:{c}\""));
        assert_eq!(attr(ch, "Name"), Some(*name));
    }
    let t0 = s.steps[0].t_unix_s;
    for (t, r) in s.steps.iter().enumerate() {
        for c in 0..3 {
            let p = element(
                &xml,
                "Plane",
                &format!("TheC=\"{c}\" TheZ=\"0\" TheT=\"{t}\""),
            );
            assert_eq!(
                attr(p, "PositionX").unwrap().parse::<f64>(),
                Ok(r.position_um)
            );
            assert_eq!(attr(p, "PositionXUnit"), Some("&#181;m"));
            let dt: f64 = attr(p, "DeltaT").unwrap().parse().unwrap();
            assert_eq!(dt, r.t_unix_s - t0);
            assert_eq!(attr(p, "DeltaTUnit"), Some("s"));
        }
    }
    // The session's metadata and the whole plane table ride along.
    assert!(xml.contains(&format!("<M K=\"session\">{}</M>", s.manifest.name)));
    assert!(
        xml.contains("&quot;state&quot;:&quot;finished&quot;"),
        "the manifest"
    );
    let reading = s.steps[2].interferometer_um.unwrap();
    assert!(
        xml.contains(&format!(",{reading},")),
        "plane 2's interferometer reading"
    );

    // 3 IFDs per frame, R G B, each the PNG's channel; the scale as pixels per cm.
    let mut ifds = 0;
    for r in &s.steps {
        let img = frame(&s, r.index);
        for c in 0..3 {
            if ifds > 0 {
                assert!(d.more_images());
                d.next_image().unwrap();
            }
            ifds += 1;
            assert_eq!(d.dimensions().unwrap(), (64, 40));
            let DecodingResult::U8(px) = d.read_image().unwrap() else {
                panic!("not 8-bit")
            };
            assert_eq!(px, channel(&img, c), "frame {} channel {c}", r.index);
            let Value::Rational(n, den) = d.get_tag(Tag::XResolution).unwrap() else {
                panic!("no XResolution")
            };
            let per_cm = f64::from(n) / f64::from(den);
            assert!((per_cm - 1e4 / scale).abs() < 1e-6 * per_cm, "{per_cm}");
            assert_eq!(d.get_tag_u32(Tag::ResolutionUnit).unwrap(), 3, "centimetre");
        }
    }
    assert!(!d.more_images(), "{ifds} IFDs and more");
    assert!(!dir.path().join(".out.ome.tif.partial").exists());
}

#[test]
fn ome_zarr_holds_every_pixel_with_its_scale_positions_and_times() {
    let dir = tempfile::tempdir().unwrap();
    let s = record(dir.path());
    let out = dir.path().join("out.ome.zarr");
    export(&s.dir, Format::OmeZarr, &out).unwrap();
    let scale = s.manifest.rig.scale_um_per_px;
    let read_json = |p: &Path| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
    };
    let group = read_json(&out.join("zarr.json"));
    assert_eq!(group["zarr_format"], 3);
    assert_eq!(group["node_type"], "group");
    let ome = &group["attributes"]["ome"];
    assert_eq!(ome["version"], "0.5");
    let ms = &ome["multiscales"][0];
    let axes: Vec<(&str, &str, Option<&str>)> = ms["axes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| {
            (
                a["name"].as_str().unwrap(),
                a["type"].as_str().unwrap(),
                a["unit"].as_str(),
            )
        })
        .collect();
    assert_eq!(
        axes,
        [
            ("t", "time", None),
            ("c", "channel", None),
            ("y", "space", Some("micrometer")),
            ("x", "space", Some("micrometer"))
        ]
    );
    let ds = &ms["datasets"][0];
    assert_eq!(ds["path"], "0");
    let tr = &ds["coordinateTransformations"][0];
    assert_eq!(tr["type"], "scale");
    assert_eq!(tr["scale"], serde_json::json!([1.0, 1.0, scale, scale]));
    let labels: Vec<&str> = ome["omero"]["channels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["label"].as_str().unwrap())
        .collect();
    assert_eq!(labels, ["R", "G", "B"]);

    let rigd = &group["attributes"]["rigd"];
    assert_eq!(rigd["session"], s.manifest.name.as_str());
    assert_eq!(rigd["manifest"]["state"], "finished");
    assert_eq!(rigd["manifest"]["job_id"], s.manifest.job_id);
    let planes = &rigd["planes"];
    for (t, r) in s.steps.iter().enumerate() {
        assert_eq!(planes["index"][t], r.index);
        assert_eq!(planes["position_um"][t].as_f64(), Some(r.position_um));
        assert_eq!(planes["axis_um"][t].as_f64(), Some(r.axis_um));
        assert_eq!(planes["interferometer_um"][t].as_f64(), r.interferometer_um);
        assert_eq!(planes["t_unix_s"][t].as_f64(), Some(r.t_unix_s));
        assert!(planes["piezo_um"][t].is_null(), "no piezo on this plan");
    }

    let array = read_json(&out.join("0/zarr.json"));
    assert_eq!(array["node_type"], "array");
    assert_eq!(array["data_type"], "uint8");
    assert_eq!(array["shape"], serde_json::json!([FRAMES, 3, 40, 64]));
    assert_eq!(
        array["chunk_grid"]["configuration"]["chunk_shape"],
        serde_json::json!([1, 3, 40, 64])
    );
    assert_eq!(
        array["dimension_names"],
        serde_json::json!(["t", "c", "y", "x"])
    );
    for (t, r) in s.steps.iter().enumerate() {
        let chunk = std::fs::read(out.join(format!("0/c/{t}/0/0/0"))).unwrap();
        let img = frame(&s, r.index);
        let want: Vec<u8> = (0..3).flat_map(|c| channel(&img, c)).collect();
        assert_eq!(chunk, want, "frame {}", r.index);
    }
    assert!(!dir.path().join(".out.ome.zarr.partial").exists());
}

#[test]
fn bad_sessions_are_refused_naming_the_session_and_frame() {
    let dir = tempfile::tempdir().unwrap();
    let s = record(dir.path());
    let out = dir.path().join("x.ome.tif");
    let name = s.dir.display().to_string();

    // An existing output is never overwritten.
    std::fs::write(&out, b"keep").unwrap();
    let e = export(&s.dir, Format::OmeTiff, &out).unwrap_err();
    assert!(matches!(e, ExportError::Exists { .. }), "{e}");
    assert_eq!(std::fs::read(&out).unwrap(), b"keep");
    std::fs::remove_file(&out).unwrap();

    // A frame of another size, then a frame that is not there: the error names the session
    // and the frame, and nothing is left behind (neither the output nor its temporary).
    let f3 = s.frame_path(3);
    let keep = std::fs::read(&f3).unwrap();
    RgbImage::new(10, 10).save(&f3).unwrap();
    let mut formats = vec![Format::OmeTiff, Format::OmeZarr];
    if rigd::export::NEXUS_BUILT {
        formats.push(Format::Nexus);
    }
    for format in formats {
        let e = export(&s.dir, format, &out).unwrap_err().to_string();
        assert!(
            e.contains(&name) && e.contains("frame 3 (frames/000003.png)"),
            "{e}"
        );
        assert!(
            e.contains("10x10 pixels where the first frame has 64x40"),
            "{e}"
        );
        assert!(!out.exists());
        assert_eq!(
            std::fs::read_dir(dir.path()).unwrap().count(),
            2,
            "only the session and the board"
        );
    }
    std::fs::remove_file(&f3).unwrap();
    let e = export(&s.dir, Format::OmeZarr, &out)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&name) && e.contains("frame 3 (frames/000003.png)"),
        "{e}"
    );

    // A symlink planted for a frame is not followed out of the session.
    let outside = dir.path().join("outside.png");
    std::fs::write(&outside, keep).unwrap();
    std::os::unix::fs::symlink(&outside, &f3).unwrap();
    let e = export(&s.dir, Format::OmeTiff, &out)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("frame 3") && e.contains("a symbolic link: not followed"),
        "{e}"
    );

    // A session whose frames were removed (as `rigctl demo` does).
    std::fs::remove_dir_all(s.dir.join("frames")).unwrap();
    let e = export(&s.dir, Format::OmeTiff, &out)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&name) && e.contains("no frames to export"),
        "{e}"
    );
}

#[test]
fn rigctl_export_writes_beside_and_says_what_it_wrote() {
    let dir = tempfile::tempdir().unwrap();
    let s = record(dir.path());
    let rigctl = env!("CARGO_BIN_EXE_rigctl");
    let run = |args: &[&str]| {
        std::process::Command::new(rigctl)
            .arg("export")
            .args(args)
            .current_dir(dir.path())
            .output()
            .unwrap()
    };
    let session = s.dir.to_str().unwrap();
    let o = run(&[session, "--format", "ome-zarr"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let want = format!("{}.ome.zarr", s.manifest.name);
    let text = String::from_utf8(o.stdout).unwrap();
    assert!(
        text.starts_with(&format!("{want}: 5 frames of 64x40 px")),
        "{text}"
    );
    assert!(dir.path().join(&want).join("0/c/4/0/0/0").is_file());
    let o = run(&[session, "--format", "ome-tiff", "--out", "a.tif", "--json"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["frames"], 5);
    assert_eq!(v["frame_size"], serde_json::json!([64, 40]));
    // Again: refused, exit 1, naming the file.
    let o = run(&[session, "--format", "ome-tiff", "--out", "a.tif"]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("a.tif: already exists"), "{err}");
}

#[cfg(not(feature = "hdf5"))]
#[test]
fn nexus_without_the_hdf5_feature_says_how_to_build_it() {
    let dir = tempfile::tempdir().unwrap();
    let s = record(dir.path());
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(["export", s.dir.to_str().unwrap(), "--format", "nexus"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("built without the cargo feature `hdf5`")
            && err.contains("libhdf5-dev")
            && err.contains("--features hdf5"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        2,
        "nothing written beside the session and the board"
    );
}
