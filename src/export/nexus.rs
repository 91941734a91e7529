//! The NeXus writer (HDF5; cargo feature `hdf5`), after the NeXus base classes:
//!
//! ```text
//! /                      NXroot   @default=entry
//! /entry                 NXentry  @default=data: title, start_time, end_time, program_name
//! /entry/instrument      NXinstrument
//!   camera               NXdetector: data uint8 [N, H, W, 3], x_pixel_size, y_pixel_size (um),
//!                        start_time [N] (s from the first exposure, @start ISO 8601)
//!   axis | piezo         NXpositioner: the job's stage, value [N] (reported), target_value [N]
//!                        (commanded), soft limits (um)
//!   piezo                NXpositioner: a plan's piezo besides the axis (only then)
//!   interferometer       NXsensor: value [N] (um; NaN where a frame has no reading)
//! /entry/data            NXdata @signal=frames @axes=[position, y, x, .]: links to the
//!                        detector's frames and times and the stage's commanded positions,
//!                        y [H] and x [W] (um: pixel i at i × scale)
//! /entry/rigd            NXcollection: the session's name, scale, planes (steps.csv's
//!                        columns) and manifest (its JSON, and as nested NXcollections)
//! ```
//!
//! Frames keep the PNG's interleaved layout (row, column, channel), so each is one
//! contiguous hyperslab of its own chunk `[1, H, W, 3]`, written and dropped before the
//! next; NeXus's `interpretation = "rgba-image"` tells readers (silx) that the last
//! dimension is the colour. Units are UDUNITS spellings, as NeXus asks: `um` (µm), `s`, `ms`.

use super::{partial_path, put_in_place, ExportError, Source};
use crate::acquisition::StageKind;
use hdf5::types::VarLenUnicode;
use hdf5::{Dataset, Group, H5Type, Location};
use hdf5_metno as hdf5;
use std::path::Path;

/// What `/entry/rigd/format` says: the layout of this module.
pub const FORMAT: &str = "rigd-export/1";
/// Micrometres, as UDUNITS (and so NeXus) spells them.
pub const UM: &str = "um";

/// Write `src` as a NeXus file at `out` (via a hidden temporary renamed into place).
pub fn write(src: &Source, out: &Path) -> Result<(), ExportError> {
    let tmp = partial_path(out);
    // A temporary left by an export that was killed: ours to remove (a symlink is unlinked,
    // never followed; create_excl then refuses anything in the way).
    let _ = std::fs::remove_file(&tmp);
    let written = write_file(src, &tmp, out);
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written?;
    put_in_place(&tmp, out)
}

fn write_file(src: &Source, tmp: &Path, out: &Path) -> Result<(), ExportError> {
    let h5 = |e: hdf5::Error| ExportError::output(out, format!("HDF5: {e}"));
    let file = hdf5::File::create_excl(tmp).map_err(h5)?;
    let entry = skeleton(src, &file).map_err(h5)?;
    let (w, h) = src.frame_size;
    let (w, h) = (w as usize, h as usize);
    let camera = entry.group("instrument/camera").map_err(h5)?;
    let frames = camera
        .new_dataset::<u8>()
        .shape((src.planes.len(), h, w, 3))
        .chunk((1, h, w, 3))
        .create("data")
        .map_err(h5)?;
    src.for_each_rgb(|t, img| {
        let view = ndarray::ArrayView4::from_shape((1, h, w, 3), img.as_raw())
            .map_err(|e| ExportError::output(out, format!("frame {t}: {e}")))?;
        frames
            .write_slice(view, ndarray::s![t..t + 1, .., .., ..])
            .map_err(h5)
    })?;
    frames_attrs(&frames).map_err(h5)?;
    data_group(src, &entry).map_err(h5)?;
    drop((frames, camera, entry));
    file.close().map_err(h5)?;
    // HDF5 closes without fsync: sync before the rename publishes the file.
    std::fs::File::open(tmp)
        .and_then(|f| f.sync_all())
        .map_err(|e| ExportError::output(out, e))
}

/// Everything but the frames and NXdata: root, entry, instrument, rigd's collection.
fn skeleton(src: &Source, file: &hdf5::File) -> hdf5::Result<Group> {
    let m = &src.session.manifest;
    let p = &src.planes;
    attr_str(file, "NX_class", "NXroot")?;
    attr_str(file, "default", "entry")?;
    attr_str(file, "creator", &format!("rigd {}", m.versions.rigd))?;
    if let Some(t) = super::ome_xml::utc_rfc3339(m.updated_unix_s) {
        attr_str(file, "file_time", &t)?;
    }
    let entry = nx_group(file, "entry", "NXentry")?;
    attr_str(&entry, "default", "data")?;
    field_str(&entry, "title", &format!("rigd session {}", m.name))?;
    field_str(&entry, "entry_identifier", &m.name)?;
    let program = field_str(&entry, "program_name", "rigd")?;
    attr_str(&program, "version", &m.versions.rigd)?;
    let times = [p.t_unix_s.first(), p.t_unix_s.last()];
    for (name, t) in ["start_time", "end_time"].into_iter().zip(times) {
        if let Some(t) = t.copied().and_then(super::ome_xml::utc_rfc3339) {
            field_str(&entry, name, &t)?;
        }
    }
    instrument(src, &entry)?;
    collection(src, &entry)?;
    Ok(entry)
}

/// NXinstrument: the camera (NXdetector, its frames added after), the stages
/// (NXpositioner) and the interferometer (NXsensor).
fn instrument(src: &Source, entry: &Group) -> hdf5::Result<()> {
    let m = &src.session.manifest;
    let p = &src.planes;
    let inst = nx_group(entry, "instrument", "NXinstrument")?;
    field_str(
        &inst,
        "name",
        &format!("rigd rig ({:?})", m.rig.mode).to_lowercase(),
    )?;
    let cam = nx_group(&inst, "camera", "NXdetector")?;
    field_str(&cam, "description", "camera on the axis, 8-bit RGB")?;
    field_str(&cam, "layout", "area")?;
    let s = src.scale_um_per_px();
    for name in ["x_pixel_size", "y_pixel_size"] {
        field_um(&cam, name, s)?;
    }
    let t0 = p.t_unix_s.first().copied().unwrap_or(0.0);
    let dt: Vec<f64> = (0..p.len()).map(|t| p.delta_t_s(t)).collect();
    let start = field_f64s(&cam, "start_time", &dt, "s")?;
    attr_str(&start, "long_name", "exposure time from the first frame's")?;
    if let Some(t) = super::ome_xml::utc_rfc3339(t0) {
        attr_str(&start, "start", &t)?;
    }
    let (stage, _) = m.job.stages();
    let limits = match stage {
        StageKind::Axis => Some(m.rig.axis_limits_um),
        StageKind::Piezo => m.rig.piezo_limits_um,
    };
    positioner(
        &inst,
        &stage.to_string(),
        &p.axis_um,
        &p.position_um,
        limits,
    )?;
    if p.has_piezo() && stage != StageKind::Piezo {
        let (reported, commanded) = (
            nan_for_none(&p.piezo_um),
            nan_for_none(&p.piezo_commanded_um),
        );
        positioner(&inst, "piezo", &reported, &commanded, m.rig.piezo_limits_um)?;
    }
    if p.interferometer_um.iter().any(Option::is_some) {
        let sensor = nx_group(&inst, "interferometer", "NXsensor")?;
        field_str(&sensor, "name", "interferometer")?;
        field_str(&sensor, "type", "laser interferometer (XL-80 log)")?;
        field_str(&sensor, "attached_to", &stage.to_string())?;
        let v = field_f64s(&sensor, "value", &nan_for_none(&p.interferometer_um), UM)?;
        attr_str(&v, "long_name", "reading at each exposure (NaN: none)")?;
    }
    Ok(())
}

/// An NXpositioner: reported `value` and commanded `target_value` per frame, in µm.
fn positioner(
    inst: &Group,
    name: &str,
    reported_um: &[f64],
    commanded_um: &[f64],
    limits_um: Option<[f64; 2]>,
) -> hdf5::Result<()> {
    let g = nx_group(inst, name, "NXpositioner")?;
    field_str(&g, "name", name)?;
    field_f64s(&g, "value", reported_um, UM)?;
    field_f64s(&g, "target_value", commanded_um, UM)?;
    if let Some([lo, hi]) = limits_um {
        field_um(&g, "soft_limit_min", lo)?;
        field_um(&g, "soft_limit_max", hi)?;
    }
    Ok(())
}

/// The signal's own attributes, once its pixels are written.
fn frames_attrs(frames: &Dataset) -> hdf5::Result<()> {
    attr_str(frames, "interpretation", "rgba-image")?;
    attr_str(
        frames,
        "long_name",
        "frames (uint8 RGB: frame, row, column, channel)",
    )
}

/// NXdata: the frames, their commanded positions and times (links into the instrument),
/// the pixel axes in µm.
fn data_group(src: &Source, entry: &Group) -> hdf5::Result<()> {
    let data = nx_group(entry, "data", "NXdata")?;
    let stage = src.session.manifest.job.stages().0.to_string();
    let links = [
        ("instrument/camera/data", "frames"),
        ("instrument/camera/start_time", "time"),
    ];
    let position = format!("instrument/{stage}/target_value");
    for (target, name) in links.into_iter().chain([(position.as_str(), "position")]) {
        data.link_hard(&format!("/entry/{target}"), name)?;
        let linked = entry.dataset(target)?;
        attr_str(&linked, "target", &format!("/entry/{target}"))?;
    }
    let (w, h) = src.frame_size;
    let s = src.scale_um_per_px();
    let px = |n: u32| (0..n).map(|i| f64::from(i) * s).collect::<Vec<f64>>();
    field_f64s(&data, "y", &px(h), UM)?;
    field_f64s(&data, "x", &px(w), UM)?;
    attr_str(&data, "signal", "frames")?;
    attr_strs(&data, "axes", &["position", "y", "x", "."])?;
    for (axis, dim) in [("position", 0), ("time", 0), ("y", 1), ("x", 2)] {
        data.new_attr::<i32>()
            .shape(())
            .create(format!("{axis}_indices").as_str())?
            .write_scalar(&dim)?;
    }
    Ok(())
}

/// `/entry/rigd`: the session's name and scale, steps.csv's columns under their own names
/// and units, and the manifest (JSON text, and as nested NXcollections with units).
fn collection(src: &Source, entry: &Group) -> hdf5::Result<()> {
    let m = &src.session.manifest;
    let p = &src.planes;
    let g = nx_group(entry, "rigd", "NXcollection")?;
    field_str(&g, "format", FORMAT)?;
    field_str(&g, "session", &m.name)?;
    field_um(&g, "scale_um_per_px", src.scale_um_per_px())?;
    let planes = nx_group(&g, "planes", "NXcollection")?;
    let ints = |v: &[u32]| v.iter().map(|&x| i64::from(x)).collect::<Vec<i64>>();
    planes
        .new_dataset_builder()
        .with_data(&ints(&p.index))
        .create("index")?;
    planes
        .new_dataset_builder()
        .with_data(&ints(&p.run))
        .create("run")?;
    planes
        .new_dataset_builder()
        .with_data(&ints(&p.repeat))
        .create("repeat")?;
    let cases = p
        .case
        .iter()
        .map(|c| vlen(c))
        .collect::<hdf5::Result<Vec<_>>>()?;
    planes
        .new_dataset_builder()
        .with_data(&cases)
        .create("case")?;
    field_f64s(&planes, "position_um", &p.position_um, UM)?;
    field_f64s(&planes, "axis_um", &p.axis_um, UM)?;
    for (name, col) in [
        ("interferometer_um", &p.interferometer_um),
        ("piezo_commanded_um", &p.piezo_commanded_um),
        ("piezo_um", &p.piezo_um),
    ] {
        field_f64s(&planes, name, &nan_for_none(col), UM)?;
    }
    let t = field_f64s(&planes, "t_unix_s", &p.t_unix_s, "s")?;
    attr_str(&t, "start", "1970-01-01T00:00:00Z")?;
    let json = serde_json::to_value(m).map_err(|e| e.to_string())?;
    field_str(&g, "manifest_json", &json.to_string())?;
    json_collection(&g, "manifest", &json)
}

/// A JSON object as an NXcollection: objects nest, strings, numbers and booleans become
/// fields (units from the key's suffix: `_um`, `_ms`, `_s`), arrays of numbers 1-D fields,
/// other arrays their JSON text; nulls are left out.
fn json_collection(parent: &Group, name: &str, v: &serde_json::Value) -> hdf5::Result<()> {
    use serde_json::Value;
    let Value::Object(map) = v else {
        return Err(format!("{name}: not a JSON object").into());
    };
    let g = nx_group(parent, name, "NXcollection")?;
    for (key, v) in map {
        // An HDF5 name cannot hold '/'; our keys never do, a board's map keys might.
        let key = key.replace('/', "_");
        let ds = match v {
            Value::Null => continue,
            Value::Object(_) => {
                json_collection(&g, &key, v)?;
                continue;
            }
            Value::Bool(b) => field_num(&g, &key, *b)?,
            Value::Number(n) => match n.as_i64() {
                Some(i) => field_num(&g, &key, i)?,
                None => field_num(&g, &key, n.as_f64().unwrap_or(f64::NAN))?,
            },
            Value::String(s) => field_str(&g, &key, s)?,
            Value::Array(a) if !a.is_empty() && a.iter().all(Value::is_number) => {
                let xs: Vec<f64> = a.iter().filter_map(Value::as_f64).collect();
                g.new_dataset_builder()
                    .with_data(&xs)
                    .create(key.as_str())?
            }
            Value::Array(_) => field_str(&g, &key, &v.to_string())?,
        };
        if let Some(u) = unit_of(&key) {
            attr_str(&ds, "units", u)?;
        }
    }
    Ok(())
}

/// The unit a manifest key's suffix names (rigd's keys carry their units).
pub fn unit_of(key: &str) -> Option<&'static str> {
    [("_um_per_px", UM), ("_um", UM), ("_ms", "ms"), ("_s", "s")]
        .into_iter()
        .find(|(suffix, _)| key.ends_with(suffix))
        .map(|(_, u)| u)
}

fn nan_for_none(v: &[Option<f64>]) -> Vec<f64> {
    v.iter().map(|x| x.unwrap_or(f64::NAN)).collect()
}

fn vlen(s: &str) -> hdf5::Result<VarLenUnicode> {
    s.parse()
        .map_err(|e| format!("{s:?}: not an HDF5 string: {e}").into())
}

fn nx_group(parent: &Group, name: &str, class: &str) -> hdf5::Result<Group> {
    let g = parent.create_group(name)?;
    attr_str(&g, "NX_class", class)?;
    Ok(g)
}

/// A variable-length UTF-8 string attribute (h5py reads a `str`).
fn attr_str(loc: &Location, name: &str, value: &str) -> hdf5::Result<()> {
    loc.new_attr::<VarLenUnicode>()
        .shape(())
        .create(name)?
        .write_scalar(&vlen(value)?)
}

fn attr_strs(loc: &Location, name: &str, values: &[&str]) -> hdf5::Result<()> {
    let v = values
        .iter()
        .map(|s| vlen(s))
        .collect::<hdf5::Result<Vec<_>>>()?;
    loc.new_attr_builder().with_data(&v).create(name).map(drop)
}

fn field_str(g: &Group, name: &str, value: &str) -> hdf5::Result<Dataset> {
    let ds = g.new_dataset::<VarLenUnicode>().shape(()).create(name)?;
    ds.write_scalar(&vlen(value)?)?;
    Ok(ds)
}

fn field_num<T: H5Type>(g: &Group, name: &str, value: T) -> hdf5::Result<Dataset> {
    let ds = g.new_dataset::<T>().shape(()).create(name)?;
    ds.write_scalar(&value)?;
    Ok(ds)
}

/// A scalar length in µm.
fn field_um(g: &Group, name: &str, value_um: f64) -> hdf5::Result<()> {
    let ds = field_num(g, name, value_um)?;
    attr_str(&ds, "units", UM)
}

fn field_f64s(g: &Group, name: &str, values: &[f64], units: &str) -> hdf5::Result<Dataset> {
    let ds = g.new_dataset_builder().with_data(values).create(name)?;
    attr_str(&ds, "units", units)?;
    Ok(ds)
}
