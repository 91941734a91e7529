"""A session folder on disk (docs/sessions.md) as numpy, pandas and xarray."""

from __future__ import annotations

import io
import json
import os
from functools import cached_property
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import numpy.typing as npt
import pandas as pd
import xarray as xr
from PIL import Image

Json = dict[str, Any]
Frames = npt.NDArray[np.uint8]

#: The offsets table's columns, in order.
OFFSET_COLUMNS = [
    "run", "case", "repeat", "k", "target", "dx_um", "dy_um", "u_dx_um", "u_dy_um",
    "u_a_dx_um", "u_a_dy_um", "nominal_dx_um", "nominal_dy_um", "dx_px", "dy_px",
    "centre_x_px", "centre_y_px", "frames",
]  # fmt: skip

#: results.csv's columns (docs/sessions.md), in order: offsets and their standard
#: uncertainties, the nominal offsets and the bias (measured - nominal) in µm.
RESULTS_COLUMNS = [
    "run", "case", "repeat", "target", "dx_um", "dy_um", "u_dx_um", "u_dy_um",
    "nominal_dx_um", "nominal_dy_um", "bias_dx_um", "bias_dy_um", "frames", "k",
    "estimator", "combine", "registration",
]  # fmt: skip
_RESULTS_TEXT = ["case", "target", "estimator", "combine", "registration"]


def read_results_csv(path: str | os.PathLike[str]) -> pd.DataFrame:
    """A results.csv (a session's, or `rigctl process --out`'s) as a DataFrame: empty cells
    (a figure not known) are NaN in the number columns and "" in the text ones."""
    df = pd.read_csv(
        path, dtype={c: str for c in _RESULTS_TEXT}, keep_default_na=False, na_values=[""]
    )
    missing = [c for c in RESULTS_COLUMNS if c not in df.columns]
    if missing:
        raise ValueError(f"{path}: not a results.csv (no column {', '.join(missing)})")
    for c in _RESULTS_TEXT:
        df[c] = df[c].fillna("")
    return df


def _complete_lines(path: Path) -> str:
    """The file's text without an unterminated last line (a crash mid-append leaves one)."""
    text = path.read_text(encoding="utf-8")
    if text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    return text


class Session:
    """`Session(path)`: one session folder. Everything is read on first use and kept."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        if not (self.path / "manifest.json").is_file():
            raise FileNotFoundError(f"{self.path}: not a rigd session (no manifest.json)")

    def __repr__(self) -> str:
        return f"Session({str(self.path)!r})"

    # -- metadata -----------------------------------------------------------------------

    @cached_property
    def manifest(self) -> Json:
        """manifest.json as a dict (job, plan, rig, interferometer, versions, state ...)."""
        data: Json = json.loads((self.path / "manifest.json").read_text(encoding="utf-8"))
        return data

    @property
    def name(self) -> str:
        return str(self.manifest.get("name", self.path.name))

    @property
    def job_id(self) -> int:
        return int(self.manifest["job_id"])

    @property
    def state(self) -> str:
        return str(self.manifest.get("state"))

    @property
    def job(self) -> Json:
        job: Json = self.manifest.get("job", {})
        return job

    @property
    def pixel_size_um(self) -> float:
        """The rig's scale: µm of the board per frame pixel."""
        return float(self.manifest["rig"]["scale_um_per_px"])

    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height) in px."""
        w, h = self.manifest["rig"]["frame_size"]
        return int(w), int(h)

    # -- tables -------------------------------------------------------------------------

    @cached_property
    def steps(self) -> pd.DataFrame:
        """steps.csv: one row per captured frame (`index`, `position_um` (commanded),
        `axis_um`, `interferometer_um` (NaN without a reading), `t_unix_s`, ...)."""
        text = _complete_lines(self.path / "steps.csv")
        return pd.read_csv(io.StringIO(text), dtype={"case": str})

    @cached_property
    def interferometer(self) -> pd.DataFrame:
        """interferometer.csv (`t_unix_s`, `position_um`, `sample`); empty without one."""
        path = self.path / "interferometer.csv"
        if not path.is_file():
            return pd.DataFrame({"t_unix_s": [], "position_um": [], "sample": []})
        return pd.read_csv(io.StringIO(_complete_lines(path)))

    @cached_property
    def result(self) -> Optional[Json]:
        """result.json as a dict (`runs`, `study`), None before a job processed."""
        path = self.path / "result.json"
        if not path.is_file():
            return None
        data: Json = json.loads(path.read_text(encoding="utf-8"))
        return data

    @cached_property
    def offsets(self) -> pd.DataFrame:
        """Every target measured in every run, one row each (OFFSET_COLUMNS): the offset
        of the inner centre from the outer one, µm and px; its combined standard
        uncertainty `u_*` (result.json's `u_um`) and the frames' share of it `u_a_*`
        (`u_a_um`), both in the offset's own scale; the nominal offset, named as
        results.csv names it."""
        rows: list[Json] = []
        for run in (self.result or {}).get("runs", []):
            for obj in (run.get("result") or {}).get("objects", []):
                rows.append(_offset_row(run, obj))
        return pd.DataFrame(rows, columns=OFFSET_COLUMNS)

    def results(self) -> pd.DataFrame:
        """results.csv: one row per (run, case, repeat, target) with dx_um, dy_um, their
        combined standard uncertainties u_dx_um, u_dy_um (result.json's `u_um`: the frames'
        scatter and the scale or calibration, docs/calibration.md), nominal_dx_um/nominal_dy_um and
        bias_dx_um/bias_dy_um (NaN when not known), frames, k and the processing settings
        (RESULTS_COLUMNS). FileNotFoundError for a session that has none (not processed
        yet, or written before rigd wrote it: `offsets` reads result.json instead)."""
        path = self.path / "results.csv"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no results table in this session")
        return read_results_csv(path)

    # -- frames -------------------------------------------------------------------------

    @property
    def indices(self) -> list[int]:
        """The job's frame indices that were captured (steps.csv's `index`)."""
        return [int(i) for i in self.steps["index"]]

    def __len__(self) -> int:
        return len(self.steps)

    @property
    def frames_dir(self) -> Path:
        """Where the frames are: `frames/`, or for a replay the `frames/` of the session
        its manifest's `frames_from` names (a sibling folder: replays copy no frame)."""
        src = self.manifest.get("frames_from")
        if src is None:
            return self.path / "frames"
        if not isinstance(src, str) or src in ("", ".", "..") or "/" in src:
            raise ValueError(f"{self.path}: frames_from {src!r} is not a session name")
        return self.path.parent / src / "frames"

    def frame_path(self, index: int) -> Path:
        return self.frames_dir / f"{index:06d}.png"

    def frame(self, index: int) -> Frames:
        """Frame `index` (the job's numbering) as an (h, w, 3) uint8 array."""
        if not self.frames_dir.is_dir():
            raise FileNotFoundError(
                f"{self.path}: its frames are gone ({self.frames_dir} is missing): "
                "`rigctl demo` removes them unless run with --keep"
            )
        with Image.open(self.frame_path(index)) as im:
            return np.asarray(im.convert("RGB"), dtype=np.uint8)

    def frames(self, indices: Optional[Sequence[int]] = None) -> Frames:
        """Frames (all captured, or `indices`) as one (n, h, w, 3) uint8 array, decoded now."""
        idx = self.indices if indices is None else list(indices)
        w, h = self.frame_size
        out = np.empty((len(idx), h, w, 3), dtype=np.uint8)
        for n, i in enumerate(idx):
            out[n] = self.frame(i)
        return out

    def to_xarray(self, indices: Optional[Sequence[int]] = None) -> xr.DataArray:
        """The frames as a DataArray with dims (frame, y, x, channel): per-frame coordinates
        `position_um` (commanded), `axis_um`, `interferometer_um`, `t_unix_s`, `time`,
        `run`, `case`, `repeat`; `x_um`/`y_um` the pixel centres on the board; the pixel
        size and units in attrs."""
        steps = self.steps.set_index("index", drop=False)
        idx = self.indices if indices is None else list(indices)
        rows = steps.loc[idx]
        w, h = self.frame_size
        um = {"units": "um"}
        per_frame: dict[str, Any] = {
            "position_um": ("frame", rows["position_um"].to_numpy(float), um | {"long_name": "commanded position"}),
            "axis_um": ("frame", rows["axis_um"].to_numpy(float), um | {"long_name": "axis position (controller)"}),
            "interferometer_um": ("frame", rows["interferometer_um"].to_numpy(float), um | {"long_name": "interferometer reading"}),
            "t_unix_s": ("frame", rows["t_unix_s"].to_numpy(float), {"units": "s", "long_name": "exposure time, Unix seconds"}),
            "time": ("frame", pd.to_datetime(rows["t_unix_s"].to_numpy(float), unit="s").to_numpy()),
            "run": ("frame", rows["run"].to_numpy(int)),
            "case": ("frame", rows["case"].to_numpy(str)),
            "repeat": ("frame", rows["repeat"].to_numpy(int)),
        }  # fmt: skip
        for col in ("piezo_commanded_um", "piezo_um"):  # a plan that moves the piezo
            if col in rows.columns:
                per_frame[col] = ("frame", rows[col].to_numpy(float), um)
        coords: dict[str, Any] = {
            "frame": ("frame", np.asarray(idx, dtype=int)),
            "y": ("y", np.arange(h)),
            "x": ("x", np.arange(w)),
            "channel": ("channel", ["R", "G", "B"]),
            "x_um": ("x", (np.arange(w) + 0.5) * self.pixel_size_um, um),
            "y_um": ("y", (np.arange(h) + 0.5) * self.pixel_size_um, um),
            **per_frame,
        }
        attrs = {
            "session": self.name,
            "job_id": self.job_id,
            "state": self.state,
            "pixel_size_um": self.pixel_size_um,
            "pixel_size_units": "um",
            "units": "DN (8-bit)",
            "rigd": str(self.manifest.get("versions", {}).get("rigd", "")),
        }
        return xr.DataArray(
            self.frames(idx), dims=("frame", "y", "x", "channel"), coords=coords,
            name="frames", attrs=attrs,
        )  # fmt: skip


def _pair(v: Any) -> tuple[float, float]:
    if isinstance(v, (list, tuple)) and len(v) == 2 and all(x is not None for x in v):
        return float(v[0]), float(v[1])
    return float("nan"), float("nan")


def _offset_row(run: Json, obj: Json) -> Json:
    dx, dy = _pair(obj.get("offset_um"))
    ux, uy = _pair(obj.get("u_um"))
    ax, ay = _pair(obj.get("u_a_um"))
    nx, ny = _pair(obj.get("nominal_um"))
    px, py = _pair(obj.get("offset_px"))
    cx, cy = _pair(obj.get("centre_px"))
    return {
        "run": run.get("run"), "case": run.get("case"), "repeat": run.get("repeat"),
        "k": run.get("k"), "target": obj.get("name"), "dx_um": dx, "dy_um": dy,
        "u_dx_um": ux, "u_dy_um": uy, "u_a_dx_um": ax, "u_a_dy_um": ay,
        "nominal_dx_um": nx, "nominal_dy_um": ny,
        "dx_px": px, "dy_px": py, "centre_x_px": cx, "centre_y_px": cy,
        "frames": obj.get("frames"),
    }  # fmt: skip
