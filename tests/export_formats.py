"""Read a session's `rigctl export` files back with the reference Python readers and check
them against the session itself (tests/export_formats.sh runs this in CI):

- the frames' PNG metadata with Pillow: pHYs (as dpi) is the rig's scale, the tEXt chunks
  are steps.csv's row;
- OME-TIFF with tifffile: an OME series TCYX uint8 equal to the PNGs, PhysicalSizeX/Y the
  scale in µm, channel names R G B, each Plane's PositionX (µm) and DeltaT (s) steps.csv's;
- OME-Zarr with zarr (v3) and ome-zarr's reader: the same pixels, axes t c y x with y/x in
  micrometre, the scale transform, the channel labels, rigd's per-plane table;
- NeXus (given pairs after the OME files; rigctl built with the `hdf5` feature) with h5py:
  the NeXus classes, frames N x H x W x 3 uint8 equal to the PNGs, pixel size and axes in
  um, the stage's, piezo's and interferometer's positions and the times steps.csv's, the
  manifest; and silx's NXdata reader finds the default plot (signal, axes, rgba-image).

Usage: python export_formats.py SESSION_DIR OUT.ome.tif OUT.ome.zarr [SESSION_DIR OUT.nxs]...
"""

from __future__ import annotations

import csv
import json
import math
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import tifffile
import zarr
from ome_zarr.io import parse_url
from ome_zarr.reader import Reader
from PIL import Image

OME = {"ome": "http://www.openmicroscopy.org/Schemas/OME/2016-06"}


def check(cond: bool, what: str) -> None:
    if not cond:
        raise SystemExit(f"export_formats: FAILED: {what}")


def opt(v: str) -> float | None:
    return float(v) if v != "" else None


def load_session(d: Path) -> tuple[dict, list[dict], np.ndarray]:
    manifest = json.loads((d / "manifest.json").read_text())
    with open(d / "steps.csv", newline="") as f:
        steps = list(csv.DictReader(f))
    check(len(steps) > 0, "the session has frames")
    frames = []
    scale = manifest["rig"]["scale_um_per_px"]
    for row in steps:
        with Image.open(d / "frames" / f"{int(row['index']):06d}.png") as im:
            frames.append(np.asarray(im.convert("RGB")))
            # pHYs in pixels per metre, as Pillow's dots per inch.
            dpi = im.info.get("dpi")
            check(dpi is not None, f"frame {row['index']}: a pHYs chunk")
            want = round(1e6 / scale) * 0.0254
            check(abs(dpi[0] - want) < 1e-3 and abs(dpi[1] - want) < 1e-3,
                  f"frame {row['index']}: dpi {dpi} is the scale's {want}")  # fmt: skip
            text = im.text  # type: ignore[attr-defined]
            check(text.get("session") == manifest["name"], f"frame {row['index']}: session")
            check(text.get("index") == row["index"], f"frame {row['index']}: index")
            for key in ("position_um", "axis_um", "t_unix_s", "interferometer_um"):
                check(opt(text.get(key, "")) == opt(row[key]),
                      f"frame {row['index']}: {key} {text.get(key)} != steps.csv {row[key]}")  # fmt: skip
    # frames as (t, c, y, x)
    return manifest, steps, np.stack(frames).transpose(0, 3, 1, 2)


def check_tiff(path: Path, manifest: dict, steps: list[dict], frames: np.ndarray) -> None:
    scale = manifest["rig"]["scale_um_per_px"]
    with tifffile.TiffFile(path) as tf:
        check(tf.is_ome, "tifffile reads it as OME-TIFF")
        series = tf.series[0]
        check(series.axes == "TCYX", f"series axes {series.axes}")
        check(series.shape == frames.shape, f"series shape {series.shape} != {frames.shape}")
        check(series.dtype == np.uint8, f"dtype {series.dtype}")
        check(np.array_equal(series.asarray(), frames), "OME-TIFF pixels equal the PNGs")
        xml = tf.ome_metadata
    assert xml is not None
    root = ET.fromstring(xml)
    px = root.find(".//ome:Pixels", OME)
    assert px is not None
    for ax in ("X", "Y"):
        check(float(px.get(f"PhysicalSize{ax}", "nan")) == scale, f"PhysicalSize{ax} is {scale}")
        check(px.get(f"PhysicalSize{ax}Unit") == "µm", f"PhysicalSize{ax}Unit µm")
    names = [c.get("Name") for c in px.findall("ome:Channel", OME)]
    check(names == ["R", "G", "B"], f"channel names {names}")
    planes = px.findall("ome:Plane", OME)
    check(len(planes) == 3 * len(steps), f"{len(planes)} planes")
    t0 = float(steps[0]["t_unix_s"])
    for p in planes:
        row = steps[int(p.get("TheT", "-1"))]
        check(float(p.get("PositionX", "nan")) == float(row["position_um"]),
              f"plane T={p.get('TheT')} PositionX is steps.csv's position_um")  # fmt: skip
        check(p.get("PositionXUnit") == "µm", "PositionXUnit µm")
        dt = float(p.get("DeltaT", "nan"))
        check(math.isclose(dt, float(row["t_unix_s"]) - t0, abs_tol=1e-6) and p.get("DeltaTUnit") == "s",
              f"plane T={p.get('TheT')} DeltaT")  # fmt: skip
    ann = {m.get("K"): m.text for m in root.iterfind(".//ome:MapAnnotation/ome:Value/ome:M", OME)}
    check(ann.get("session") == manifest["name"], "the annotation names the session")
    check(json.loads(ann["manifest"] or "{}")["job"] == manifest["job"], "the annotation's manifest")
    print(f"export_formats: OME-TIFF {path.name}: tifffile {tifffile.__version__} reads {series.shape} OK")


def check_zarr(path: Path, manifest: dict, steps: list[dict], frames: np.ndarray) -> None:
    scale = manifest["rig"]["scale_um_per_px"]
    group = zarr.open_group(str(path), mode="r")
    arr = group["0"]
    check(arr.shape == frames.shape and arr.dtype == np.uint8, f"zarr array {arr.shape} {arr.dtype}")
    check(np.array_equal(arr[:], frames), "zarr pixels equal the PNGs")
    attrs = group.attrs.asdict()
    ms = attrs["ome"]["multiscales"][0]
    units = {a["name"]: a.get("unit") for a in ms["axes"]}
    check(units == {"t": None, "c": None, "y": "micrometer", "x": "micrometer"}, f"axes {units}")
    planes = attrs["rigd"]["planes"]
    for t, row in enumerate(steps):
        for key in ("position_um", "axis_um", "t_unix_s", "interferometer_um"):
            check(planes[key][t] == opt(row[key]), f"rigd.planes.{key}[{t}] is steps.csv's")

    # ome-zarr's own reader: the image node, its pixels, axes, scale and channel names.
    nodes = list(Reader(parse_url(str(path)))())
    check(len(nodes) >= 1, "ome-zarr finds the image")
    image = nodes[0]
    check(np.array_equal(np.asarray(image.data[0]), frames), "ome-zarr's pixels equal the PNGs")
    md = image.metadata
    axes = [(a["name"], a.get("unit")) for a in md["axes"]]
    check(axes == [("t", None), ("c", None), ("y", "micrometer"), ("x", "micrometer")], f"axes {axes}")
    check(md["coordinateTransformations"][0][0]["scale"] == [1.0, 1.0, scale, scale], "scale")
    check(md.get("channel_names") == ["R", "G", "B"], f"channel names {md.get('channel_names')}")
    print(f"export_formats: OME-Zarr {path.name}: zarr {zarr.__version__} and ome-zarr read {arr.shape} OK")


def same(got: np.ndarray, want: list[float | None]) -> bool:
    """`got` equals `want`, NaN where `want` has no value (how the file writes a missing one)."""
    w = np.array([np.nan if v is None else v for v in want], dtype=np.float64)
    return got.shape == w.shape and bool(np.array_equal(got, w, equal_nan=True))


def attr(obj, name: str) -> str:  # noqa: ANN001 (an h5py object)
    v = obj.attrs[name]
    return v.decode() if isinstance(v, bytes) else str(v)


def check_nexus(path: Path, manifest: dict, steps: list[dict], frames: np.ndarray) -> None:
    import h5py
    from silx.io.nxdata import get_default

    scale = manifest["rig"]["scale_um_per_px"]
    col = lambda key: [opt(r[key]) for r in steps]  # noqa: E731
    with h5py.File(path, "r") as f:
        check(attr(f, "NX_class") == "NXroot" and attr(f, "default") == "entry", "NXroot, @default")
        entry = f["entry"]
        check(attr(entry, "NX_class") == "NXentry", "NXentry")
        data = entry["data"]
        check(attr(data, "NX_class") == "NXdata" and attr(data, "signal") == "frames", "NXdata @signal")
        axes = [a.decode() if isinstance(a, bytes) else a for a in data.attrs["axes"]]
        check(axes == ["position", "y", "x", "."], f"NXdata @axes {axes}")
        sig = data["frames"]
        want = frames.transpose(0, 2, 3, 1)  # (t, y, x, c)
        check(sig.shape == want.shape and sig.dtype == np.uint8, f"frames {sig.shape} {sig.dtype}")
        check(np.array_equal(sig[()], want), "NeXus frames equal the PNGs")
        for name in ("x", "y", "position"):
            check(attr(data[name], "units") == "um", f"NXdata/{name} @units um")
        check(np.array_equal(data["x"][:], np.arange(want.shape[2]) * scale), "NXdata/x is i x scale")
        check(same(data["position"][:], col("position_um")), "NXdata/position is steps.csv's position_um")
        t0 = float(steps[0]["t_unix_s"])
        dt = [float(r["t_unix_s"]) - t0 for r in steps]
        check(np.allclose(data["time"][:], dt, rtol=0, atol=1e-9) and attr(data["time"], "units") == "s",
              "NXdata/time (s) from the first exposure")  # fmt: skip
        inst = entry["instrument"]
        cam = inst["camera"]
        check(attr(cam, "NX_class") == "NXdetector", "NXdetector")
        for name in ("x_pixel_size", "y_pixel_size"):
            check(cam[name][()] == scale and attr(cam[name], "units") == "um", f"NXdetector/{name} {scale} um")
        stage = inst["axis"]  # the sessions tests/export_formats.sh records scan the axis
        check(attr(stage, "NX_class") == "NXpositioner", "the stage is an NXpositioner")
        check(same(stage["target_value"][:], col("position_um")), "stage target_value is position_um")
        check(same(stage["value"][:], col("axis_um")) and attr(stage["value"], "units") == "um",
              "stage value (um) is axis_um")  # fmt: skip
        if any(v is not None for v in col("interferometer_um")):
            v = inst["interferometer"]["value"]
            check(same(v[:], col("interferometer_um")) and attr(v, "units") == "um", "interferometer value (um)")
        has_piezo = any(v is not None for v in col("piezo_commanded_um"))
        check(("piezo" in inst) == has_piezo, f"a piezo NXpositioner only with piezo columns ({has_piezo})")
        if has_piezo:
            check(same(inst["piezo"]["target_value"][:], col("piezo_commanded_um")), "piezo target_value")
            check(same(inst["piezo"]["value"][:], col("piezo_um")), "piezo value")
        rigd = entry["rigd"]
        check(same(rigd["planes"]["t_unix_s"][:], col("t_unix_s")), "rigd/planes/t_unix_s")
        check(json.loads(rigd["manifest_json"][()])["job"] == manifest["job"], "rigd/manifest_json's job")
        board = manifest["rig"]["board"]["name"]
        check(rigd["manifest"]["rig"]["board"]["name"][()].decode() == board, "rigd/manifest/rig/board/name")

        # silx, as its viewer finds the plot: @default to NXdata, the signal and its axes.
        nx = get_default(f)
        check(nx is not None and nx.is_valid, "silx finds a valid default NXdata")
        check(nx.signal_dataset_name == "frames" and nx.interpretation == "rgba-image",
              f"silx: signal {nx.signal_dataset_name}, interpretation {nx.interpretation}")  # fmt: skip
        names = nx.axes_dataset_names
        check(names == ["position", "y", "x", None], f"silx: axes {names}")
    print(f"export_formats: NeXus {path.name}: h5py {h5py.__version__} and silx read {sig.shape} OK")


def main() -> None:
    session, tif, zarr_path = (Path(a) for a in sys.argv[1:4])
    manifest, steps, frames = load_session(session)
    print(f"export_formats: {session.name}: {len(steps)} frames, PNG pHYs and tEXt OK (Pillow)")
    check_tiff(tif, manifest, steps, frames)
    check_zarr(zarr_path, manifest, steps, frames)
    rest = sys.argv[4:]
    check(len(rest) % 2 == 0, "NeXus files come as SESSION_DIR OUT.nxs pairs")
    for s, nxs in zip(rest[::2], rest[1::2]):
        manifest, steps, frames = load_session(Path(s))
        check_nexus(Path(nxs), manifest, steps, frames)


if __name__ == "__main__":
    main()
