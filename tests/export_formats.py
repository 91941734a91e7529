"""Read a session's `rigctl export` files back with the reference Python readers and check
them against the session itself (tests/export_formats.sh runs this in CI):

- the frames' PNG metadata with Pillow: pHYs (as dpi) is the rig's scale, the tEXt chunks
  are steps.csv's row;
- OME-TIFF with tifffile: an OME series TCYX uint8 equal to the PNGs, PhysicalSizeX/Y the
  scale in µm, channel names R G B, each Plane's PositionX (µm) and DeltaT (s) steps.csv's;
- OME-Zarr with zarr (v3) and ome-zarr's reader: the same pixels, axes t c y x with y/x in
  micrometre, the scale transform, the channel labels, rigd's per-plane table.

Usage: python export_formats.py SESSION_DIR OUT.ome.tif OUT.ome.zarr
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


def main() -> None:
    session, tif, zarr_path = (Path(a) for a in sys.argv[1:4])
    manifest, steps, frames = load_session(session)
    print(f"export_formats: {session.name}: {len(steps)} frames, PNG pHYs and tEXt OK (Pillow)")
    check_tiff(tif, manifest, steps, frames)
    check_zarr(zarr_path, manifest, steps, frames)


if __name__ == "__main__":
    main()
