//! The OME-Zarr 0.5 writer (a Zarr v3 folder):
//!
//! ```text
//! NAME.ome.zarr/zarr.json      group: attributes.ome (multiscales, omero) and attributes.rigd
//! NAME.ome.zarr/0/zarr.json    the array: uint8, shape [t, c, y, x] = [frames, 3, H, W]
//! NAME.ome.zarr/0/c/T/0/0/0    frame T's chunk: [1, 3, H, W] raw bytes (the `bytes` codec)
//! ```
//!
//! One resolution level (the frames as taken), axes `t` (the frame number: real times are
//! per plane in `rigd.planes.t_unix_s`), `c` (R, G, B) and `y`, `x` in micrometres with the
//! scale as their `coordinateTransformations`. `attributes.rigd` carries the per-plane
//! table (`planes`: positions in µm, times in s) and the session's manifest.
//!
//! Written by hand rather than with the `zarrs`/`ome_zarr_metadata` crates: both turn on
//! serde_json's `preserve_order`, which would change the key order of every JSON object
//! rigd builds (the generated protocol schema among them); the format here is three small
//! JSON documents and raw chunk files.

use super::{partial_path, put_in_place, ExportError, Source};
use serde_json::json;
use std::fs;
use std::io::Write;
use std::path::Path;

/// The OME-Zarr version written.
pub const OME_ZARR_VERSION: &str = "0.5";
/// The array's folder inside the group (the one resolution level).
pub const ARRAY: &str = "0";

/// Write `src` as OME-Zarr at `out` (a hidden temporary folder renamed into place).
pub fn write(src: &Source, out: &Path) -> Result<(), ExportError> {
    let tmp = partial_path(out);
    remove_leftover(&tmp)
        .map_err(|e| ExportError::output(out, format!("cannot remove {}: {e}", tmp.display())))?;
    let written = write_tree(src, &tmp);
    if written.is_err() {
        let _ = fs::remove_dir_all(&tmp);
    }
    written.map_err(|e| match e {
        // Name the export, not its temporary.
        ExportError::Output { message, .. } => ExportError::output(out, message),
        e => e,
    })?;
    put_in_place(&tmp, out)
}

/// A temporary left by an export that was killed: ours to remove (a symlink is unlinked,
/// not followed).
fn remove_leftover(tmp: &Path) -> std::io::Result<()> {
    match fs::symlink_metadata(tmp) {
        Ok(m) if m.is_dir() => fs::remove_dir_all(tmp),
        Ok(_) => fs::remove_file(tmp),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(e),
    }
}

fn write_tree(src: &Source, root: &Path) -> Result<(), ExportError> {
    let array = root.join(ARRAY);
    fs::create_dir(root).map_err(|e| ExportError::output(root, e))?;
    fs::create_dir_all(array.join("c")).map_err(|e| ExportError::output(&array, e))?;
    write_synced(&root.join("zarr.json"), &json_bytes(&group_metadata(src))?)?;
    write_synced(&array.join("zarr.json"), &json_bytes(&array_metadata(src))?)?;
    src.for_each_frame(|t, planar| {
        let dir = array.join("c").join(t.to_string()).join("0").join("0");
        fs::create_dir_all(&dir).map_err(|e| ExportError::output(&dir, e))?;
        write_synced(&dir.join("0"), planar)?;
        // The chunk's folders, so the rename below publishes only chunks that are on disk.
        for d in [&dir, &dir.join(".."), &dir.join("../..")] {
            crate::atomic_file::sync_dir(d).map_err(|e| ExportError::output(&dir, e))?;
        }
        Ok(())
    })?;
    for d in [array.join("c"), array, root.to_path_buf()] {
        crate::atomic_file::sync_dir(&d).map_err(|e| ExportError::output(&d, e))?;
    }
    Ok(())
}

fn json_bytes(v: &serde_json::Value) -> Result<Vec<u8>, ExportError> {
    serde_json::to_vec_pretty(v).map_err(|e| ExportError::output(Path::new("zarr.json"), e))
}

fn write_synced(path: &Path, bytes: &[u8]) -> Result<(), ExportError> {
    let mut f = fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(path)
        .map_err(|e| ExportError::output(path, e))?;
    f.write_all(bytes)
        .and_then(|()| f.sync_data())
        .map_err(|e| ExportError::output(path, e))
}

/// The group's `zarr.json`: OME's multiscales and omero blocks, and rigd's.
pub fn group_metadata(src: &Source) -> serde_json::Value {
    let s = src.scale_um_per_px();
    let channel = |label: &str, color: &str| {
        json!({
            "label": label, "color": color, "active": true, "coefficient": 1.0,
            "family": "linear", "inverted": false,
            "window": {"start": 0, "end": 255, "min": 0, "max": 255},
        })
    };
    json!({
        "zarr_format": 3,
        "node_type": "group",
        "attributes": {
            "ome": {
                "version": OME_ZARR_VERSION,
                "multiscales": [{
                    "name": src.name(),
                    "axes": [
                        {"name": "t", "type": "time"},
                        {"name": "c", "type": "channel"},
                        {"name": "y", "type": "space", "unit": "micrometer"},
                        {"name": "x", "type": "space", "unit": "micrometer"},
                    ],
                    "datasets": [{
                        "path": ARRAY,
                        "coordinateTransformations": [{"type": "scale", "scale": [1.0, 1.0, s, s]}],
                    }],
                }],
                "omero": {
                    "name": src.name(),
                    "channels": [channel("R", "FF0000"), channel("G", "00FF00"), channel("B", "0000FF")],
                    "rdefs": {"model": "color", "defaultT": 0, "defaultZ": 0},
                },
            },
            "rigd": {
                "format": "rigd-export/1",
                "session": src.name(),
                "scale_um_per_px": s,
                "units": {"position": "micrometer", "time": "second (since 1970-01-01T00:00:00Z)"},
                "planes": src.planes,
                "manifest": src.session.manifest,
            },
        },
    })
}

/// The array's `zarr.json`: uint8 `[t, c, y, x]`, a chunk per frame, no compression.
pub fn array_metadata(src: &Source) -> serde_json::Value {
    let (w, h) = src.frame_size;
    json!({
        "zarr_format": 3,
        "node_type": "array",
        "shape": [src.planes.len(), 3, h, w],
        "data_type": "uint8",
        "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [1, 3, h, w]}},
        "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
        "fill_value": 0,
        "codecs": [{"name": "bytes", "configuration": {"endian": "little"}}],
        "attributes": {},
        "dimension_names": ["t", "c", "y", "x"],
    })
}
