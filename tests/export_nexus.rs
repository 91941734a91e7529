//! `rigctl export --format nexus` (cargo feature `hdf5`): sessions recorded by the daemon on
//! the simulated rig (a line on the axis, and a grid over the axis and the piezo, both with
//! the interferometer) written as NeXus and read back through HDF5 (hdf5-metno): the NeXus
//! classes and the NXdata's signal and axes, every pixel equal to the session's PNGs, the
//! pixel size, positions and times with their units equal to the manifest's and
//! steps.csv's, the manifest's settings. (h5py and silx read the same in
//! tests/export_formats.sh.)

#![cfg(all(feature = "sim", feature = "hdf5"))]

mod support;

use hdf5::types::VarLenUnicode;
use hdf5_metno as hdf5;
use rigd::acquisition::{Grid, JobSpec, Line, ScanPlan, StageKind};
use rigd::export::{export, Format};
use rigd::session::Session;
use support::daemon::{capture_job, record_small};

const FRAMES: u32 = 5;

fn attr(loc: &hdf5::Location, name: &str) -> String {
    let a = loc.attr(name).unwrap_or_else(|e| panic!("@{name}: {e}"));
    a.read_scalar::<VarLenUnicode>()
        .unwrap()
        .as_str()
        .to_owned()
}

fn text(g: &hdf5::Group, path: &str) -> String {
    let ds = g.dataset(path).unwrap_or_else(|e| panic!("{path}: {e}"));
    ds.read_scalar::<VarLenUnicode>()
        .unwrap()
        .as_str()
        .to_owned()
}

fn floats(g: &hdf5::Group, path: &str) -> Vec<f64> {
    g.dataset(path)
        .unwrap_or_else(|e| panic!("{path}: {e}"))
        .read_raw::<f64>()
        .unwrap()
}

fn units(g: &hdf5::Group, path: &str) -> String {
    attr(&g.dataset(path).unwrap(), "units")
}

/// `want`'s values, NaN where it has none (as the file writes a missing reading).
fn same(got: &[f64], want: impl IntoIterator<Item = Option<f64>>) -> bool {
    let want: Vec<Option<f64>> = want.into_iter().collect();
    got.len() == want.len()
        && got.iter().zip(&want).all(|(g, w)| match w {
            Some(w) => g == w,
            None => g.is_nan(),
        })
}

/// Export `s` as NeXus into its parent folder and open it.
fn exported(s: &Session) -> hdf5::File {
    let out = s.dir.with_file_name("out.nxs");
    let sum = export(&s.dir, Format::Nexus, &out).unwrap();
    assert_eq!((sum.frames, sum.frame_size), (s.steps.len(), (64, 40)));
    assert!(!s.dir.with_file_name(".out.nxs.partial").exists());
    hdf5::File::open(&out).unwrap()
}

#[test]
fn nexus_holds_every_frame_with_its_scale_positions_times_and_manifest() {
    let dir = tempfile::tempdir().unwrap();
    let job = JobSpec {
        label: Some("nexus check".into()),
        ..capture_job(100.0, FRAMES, 20)
    };
    let s = record_small(dir.path(), job);
    let f = exported(&s);
    assert_eq!(attr(&f, "NX_class"), "NXroot");
    assert_eq!(attr(&f, "default"), "entry");
    let entry = f.group("entry").unwrap();
    assert_eq!(attr(&entry, "NX_class"), "NXentry");
    assert_eq!(attr(&entry, "default"), "data");
    assert_eq!(text(&entry, "entry_identifier"), s.manifest.name);
    assert!(text(&entry, "start_time").ends_with('Z'));
    check_nxdata(&entry.group("data").unwrap(), &s);
    check_instrument(&entry.group("instrument").unwrap(), &s);
    check_collection(&entry.group("rigd").unwrap(), &s);
}

/// NXdata: the signal, its axes and their dimensions, every pixel, positions and times.
fn check_nxdata(data: &hdf5::Group, s: &Session) {
    let scale = s.manifest.rig.scale_um_per_px;
    assert_eq!(attr(data, "NX_class"), "NXdata");
    assert_eq!(attr(data, "signal"), "frames");
    let axes: Vec<String> = data
        .attr("axes")
        .unwrap()
        .read_raw::<VarLenUnicode>()
        .unwrap()
        .iter()
        .map(|a| a.as_str().to_owned())
        .collect();
    assert_eq!(axes, ["position", "y", "x", "."]);
    for (axis, dim) in [("position", 0), ("time", 0), ("y", 1), ("x", 2)] {
        let a = data.attr(&format!("{axis}_indices")).unwrap();
        assert_eq!(a.read_scalar::<i32>().unwrap(), dim, "{axis}_indices");
    }
    let frames = data.dataset("frames").unwrap();
    assert_eq!(frames.shape(), [FRAMES as usize, 40, 64, 3]);
    assert_eq!(attr(&frames, "interpretation"), "rgba-image");
    let px = frames.read_raw::<u8>().unwrap();
    for (t, chunk) in px.chunks_exact(40 * 64 * 3).enumerate() {
        let png = image::open(s.frame_path(s.steps[t].index))
            .unwrap()
            .into_rgb8();
        assert_eq!(chunk, png.as_raw().as_slice(), "frame {t}");
    }
    let x = floats(data, "x");
    assert_eq!((x.len(), x[1], units(data, "x")), (64, scale, "um".into()));
    assert_eq!(floats(data, "y").len(), 40);
    let positions: Vec<f64> = s.steps.iter().map(|r| r.position_um).collect();
    assert_eq!(floats(data, "position"), positions);
    assert_eq!(units(data, "position"), "um");
    let t0 = s.steps[0].t_unix_s;
    let dt: Vec<f64> = s.steps.iter().map(|r| r.t_unix_s - t0).collect();
    assert_eq!(floats(data, "time"), dt);
    assert_eq!(units(data, "time"), "s");
}

/// NXinstrument: the detector's pixel size, the stage, the interferometer; no piezo.
fn check_instrument(inst: &hdf5::Group, s: &Session) {
    let scale = s.manifest.rig.scale_um_per_px;
    let cam = inst.group("camera").unwrap();
    assert_eq!(attr(&cam, "NX_class"), "NXdetector");
    for name in ["x_pixel_size", "y_pixel_size"] {
        let ds = cam.dataset(name).unwrap();
        assert_eq!(ds.read_scalar::<f64>().unwrap(), scale, "{name}");
        assert_eq!(attr(&ds, "units"), "um");
    }
    let start = attr(&cam.dataset("start_time").unwrap(), "start");
    let rfc3339 = time::format_description::well_known::Rfc3339;
    let start = time::OffsetDateTime::parse(&start, &rfc3339).unwrap();
    let t0 = s.steps[0].t_unix_s;
    assert!(
        (start.unix_timestamp_nanos() as f64 * 1e-9 - t0).abs() < 1e-6,
        "{start}"
    );
    let axis = inst.group("axis").unwrap();
    assert_eq!(attr(&axis, "NX_class"), "NXpositioner");
    let positions: Vec<f64> = s.steps.iter().map(|r| r.position_um).collect();
    assert_eq!(floats(&axis, "target_value"), positions);
    let reported: Vec<f64> = s.steps.iter().map(|r| r.axis_um).collect();
    assert_eq!(floats(&axis, "value"), reported);
    assert_eq!(units(&axis, "value"), "um");
    let readings = s.steps.iter().map(|r| r.interferometer_um);
    assert!(readings.clone().all(|r| r.is_some()), "the sim's XL-80");
    assert!(same(&floats(inst, "interferometer/value"), readings));
    assert_eq!(units(inst, "interferometer/value"), "um");
    assert!(inst.group("piezo").is_err(), "a line moves no piezo");
}

/// The session: steps.csv's columns, the manifest as JSON and as collections.
fn check_collection(rigd: &hdf5::Group, s: &Session) {
    let scale = s.manifest.rig.scale_um_per_px;
    assert_eq!(attr(rigd, "NX_class"), "NXcollection");
    let times: Vec<f64> = s.steps.iter().map(|r| r.t_unix_s).collect();
    assert_eq!(floats(rigd, "planes/t_unix_s"), times);
    assert_eq!(floats(rigd, "scale_um_per_px"), [scale]);
    let m: serde_json::Value = serde_json::from_str(&text(rigd, "manifest_json")).unwrap();
    assert_eq!(m["job_id"], s.manifest.job_id);
    assert_eq!(text(rigd, "manifest/job/label"), "nexus check");
    let steps = rigd.dataset("manifest/job/steps").unwrap();
    assert_eq!(steps.read_scalar::<i64>().unwrap(), i64::from(FRAMES));
    assert_eq!(floats(rigd, "manifest/job/step_um"), [100.0]);
    assert_eq!(units(rigd, "manifest/job/step_um"), "um");
    assert_eq!(units(rigd, "manifest/job/settle_ms"), "ms");
    assert_eq!(text(rigd, "manifest/rig/board/name"), "small");
    assert_eq!(units(rigd, "manifest/rig/scale_um_per_px"), "um");
}

#[test]
fn a_grid_carries_the_piezo_besides_the_axis() {
    let dir = tempfile::tempdir().unwrap();
    let line = |stage, step_um, steps| Line {
        stage,
        step_um,
        steps,
        start_um: None,
    };
    let job = JobSpec {
        plan: Some(ScanPlan::Grid(Grid {
            inner: line(StageKind::Axis, 100.0, 3),
            outer: line(StageKind::Piezo, 20.0, 2),
            snake: false,
        })),
        settle_ms: 0,
        process: false,
        ..JobSpec::default()
    };
    let s = record_small(dir.path(), job);
    let f = exported(&s);
    let inst = f.group("entry/instrument").unwrap();
    let piezo = inst.group("piezo").unwrap();
    assert_eq!(attr(&piezo, "NX_class"), "NXpositioner");
    let commanded = s.steps.iter().map(|r| r.piezo_commanded_um);
    assert!(commanded.clone().all(|p| p.is_some()));
    assert!(same(&floats(&piezo, "target_value"), commanded));
    assert!(same(
        &floats(&piezo, "value"),
        s.steps.iter().map(|r| r.piezo_um)
    ));
    assert_eq!(units(&piezo, "target_value"), "um");
    let axis: Vec<f64> = s.steps.iter().map(|r| r.position_um).collect();
    assert_eq!(floats(&inst, "axis/target_value"), axis);
    assert_eq!(f.dataset("entry/data/frames").unwrap().shape()[0], 6);
}

#[test]
fn rigctl_export_nexus_writes_name_nxs_beside() {
    let dir = tempfile::tempdir().unwrap();
    let s = record_small(dir.path(), capture_job(100.0, FRAMES, 20));
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_rigctl"))
        .args(["export", s.dir.to_str().unwrap(), "--format", "nexus"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let want = format!("{}.nxs", s.manifest.name);
    let out = String::from_utf8(o.stdout).unwrap();
    assert!(
        out.starts_with(&format!("{want}: 5 frames of 64x40 px")),
        "{out}"
    );
    let f = hdf5::File::open(dir.path().join(want)).unwrap();
    assert_eq!(
        f.dataset("entry/data/frames").unwrap().shape(),
        [5, 40, 64, 3]
    );
}
