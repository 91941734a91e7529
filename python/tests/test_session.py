"""Session(path) against a session the live daemon wrote, checked against the raw files."""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image

import rigd
from conftest import Daemon, FinishedJob


def _csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _num(s: str) -> float:
    return float(s) if s != "" else math.nan


def test_frames_match_the_manifest(finished_job: FinishedJob) -> None:
    s = rigd.Session(finished_job.path)
    manifest = json.loads((finished_job.path / "manifest.json").read_text())
    w, h = manifest["rig"]["frame_size"]
    frames = s.frames()
    assert frames.shape == (manifest["frames_captured"], h, w, 3) == (4, 720, 1280, 3)
    assert frames.dtype == np.uint8
    assert s.state == "finished" and s.job_id == finished_job.job_id
    assert s.name == finished_job.reply["session"]
    raw = np.asarray(Image.open(finished_job.path / "frames" / "000002.png").convert("RGB"))
    assert np.array_equal(frames[2], raw) and np.array_equal(s.frame(2), raw)
    assert frames[0].std() > 5  # a picture, not a blank


def test_steps_equal_steps_csv_and_the_step_events(finished_job: FinishedJob) -> None:
    s = rigd.Session(finished_job.path)
    rows = _csv_rows(finished_job.path / "steps.csv")
    df = s.steps
    assert list(df["index"]) == [int(r["index"]) for r in rows]
    for col in ("position_um", "axis_um", "interferometer_um", "t_unix_s"):
        assert np.array_equal(df[col].to_numpy(float), [_num(r[col]) for r in rows], equal_nan=True)
    events = [ev for ev in finished_job.events if isinstance(ev, rigd.Step)]
    assert list(df["position_um"]) == [ev.commanded_um for ev in events]
    assert list(df["axis_um"]) == [ev.axis_um for ev in events]
    assert list(df["interferometer_um"]) == [ev.interferometer_um for ev in events]
    assert list(df["case"]) == ["scan"] * 4


def test_interferometer_samples_give_the_steps_readings(finished_job: FinishedJob) -> None:
    s = rigd.Session(finished_job.path)
    samples = s.interferometer
    assert len(samples) == len(_csv_rows(finished_job.path / "interferometer.csv")) > 4
    assert list(samples.columns) == ["t_unix_s", "position_um", "sample"]
    # docs/sessions.md: a frame's reading is the samples' linear interpolation at its time.
    again = np.interp(s.steps["t_unix_s"], samples["t_unix_s"], samples["position_um"])
    assert np.allclose(again, s.steps["interferometer_um"], atol=1e-6, rtol=0)


def test_offsets_equal_result_json(finished_job: FinishedJob) -> None:
    s = rigd.Session(finished_job.path)
    result = json.loads((finished_job.path / "result.json").read_text())
    assert s.result == result == finished_job.reply["result"]
    objects = result["runs"][0]["result"]["objects"]
    off = s.offsets
    assert list(off.columns) == rigd.session.OFFSET_COLUMNS
    assert len(off) == len(objects) == 12
    assert list(off["target"]) == [o["name"] for o in objects]
    assert list(off["dx_um"]) == [o["offset_um"][0] for o in objects]
    assert list(off["dy_um"]) == [o["offset_um"][1] for o in objects]
    assert list(off["u_dy_um"]) == [o["u_um"][1] for o in objects]
    assert list(off["u_a_dx_um"]) == [o["u_a_um"][0] for o in objects]
    assert list(off["nominal_dx_um"]) == [o["nominal_um"][0] for o in objects]
    # u holds the frames' share and more (the scale's).
    assert (off["u_dx_um"] >= off["u_a_dx_um"]).all()
    assert set(off["run"]) == {0} and set(off["case"]) == {"scan"} and set(off["k"]) == {2}
    # The sim board's offsets are measured within a few µm of nominal.
    err = np.hypot(off["dx_um"] - off["nominal_dx_um"], off["dy_um"] - off["nominal_dy_um"])
    assert err.max() < 20


def test_results_equal_result_json(finished_job: FinishedJob) -> None:
    s = rigd.Session(finished_job.path)
    result = json.loads((finished_job.path / "result.json").read_text())
    run = result["runs"][0]
    objects = run["result"]["objects"]
    res = s.results()
    assert list(res.columns) == rigd.session.RESULTS_COLUMNS
    assert len(res) == len(objects) == 12
    assert list(res["target"]) == [o["name"] for o in objects]
    # The shortest text that reads back to the same float: equal, not close.
    assert list(res["dx_um"]) == [o["offset_um"][0] for o in objects]
    # u_dy_um is the combined standard uncertainty (GUM: type A and B), `u_um`.
    assert list(res["u_dy_um"]) == [(o.get("u_um") or o["sigma_um"])[1] for o in objects]
    assert list(res["nominal_dx_um"]) == [o["nominal_um"][0] for o in objects]
    assert list(res["bias_dy_um"]) == [o["offset_um"][1] - o["nominal_um"][1] for o in objects]
    assert set(res["case"]) == {"scan"} and set(res["k"]) == {2}
    assert set(res["estimator"]) == {run["result"]["options"]["estimator"]}
    assert set(res["registration"]) == {s.job["registration"]}


def test_a_results_csv_without_nominals_reads_as_nan(tmp_path: Path) -> None:
    path = tmp_path / "results.csv"
    path.write_text(
        ",".join(rigd.session.RESULTS_COLUMNS) + "\n0,,0,#0,1.5,-0.25,,,,,,,3,1,fit,mean,image\n"
    )
    res = rigd.session.read_results_csv(path)
    assert res["case"][0] == "" and res["target"][0] == "#0" and res["dx_um"][0] == 1.5
    assert math.isnan(res["u_dx_um"][0]) and math.isnan(res["bias_dy_um"][0])


def test_to_xarray_has_positions_time_and_pixel_size(finished_job: FinishedJob) -> None:
    s = rigd.Session(finished_job.path)
    da = s.to_xarray()
    assert da.dims == ("frame", "y", "x", "channel")
    assert da.shape == (4, 720, 1280, 3)
    assert da.attrs["pixel_size_um"] == s.manifest["rig"]["scale_um_per_px"] == 774.0
    assert da["position_um"].attrs["units"] == "um"
    assert list(da["position_um"].values) == list(s.steps["position_um"])
    assert list(da["interferometer_um"].values) == list(s.steps["interferometer_um"])
    assert list(da["frame"].values) == [0, 1, 2, 3]
    assert da["x_um"].values[1] - da["x_um"].values[0] == 774.0
    t = pd.to_datetime(s.steps["t_unix_s"], unit="s")
    assert (da["time"].values == t.to_numpy()).all()
    assert np.array_equal(da.sel(frame=3).values, s.frame(3))
    sub = s.to_xarray(indices=[1, 3])
    assert list(sub["position_um"].values) == list(s.steps["position_um"].iloc[[1, 3]])


def test_an_unterminated_last_row_is_skipped(finished_job: FinishedJob, tmp_path: Path) -> None:
    copy = tmp_path / finished_job.path.name
    shutil.copytree(finished_job.path, copy)
    with open(copy / "steps.csv", "a") as f:
        f.write("4,1200.0,0,scan,0,12")  # what a crash mid-append leaves
    with open(copy / "interferometer.csv", "a") as f:
        f.write("1796171646.9,3.")
    s = rigd.Session(copy)
    assert len(s.steps) == 4 and s.indices == [0, 1, 2, 3]
    assert len(s.interferometer) == len(rigd.Session(finished_job.path).interferometer)


def test_a_folder_without_a_manifest_is_refused(tmp_path: Path) -> None:
    import pytest

    with pytest.raises(FileNotFoundError, match="no manifest.json"):
        rigd.Session(tmp_path)


def test_a_replay_copies_no_frame_and_reads_the_recorded_ones(
    daemon: Daemon, finished_job: FinishedJob
) -> None:
    with daemon.client() as c:
        c.subscribe()
        job_id = c.replay(finished_job.path.name)["job_id"]
        for ev in c.events():
            if ev.job_id == job_id and ev.terminal:
                break
        reply = c.result(job_id)
    replay = rigd.Session(daemon.data_root / reply["session"])
    assert replay.manifest["replay_of"] == replay.manifest["frames_from"] == finished_job.path.name
    assert not (replay.path / "frames").exists()
    assert replay.frames_dir == finished_job.path / "frames"
    original = rigd.Session(finished_job.path)
    assert np.array_equal(replay.frames(), original.frames())
    assert replay.result is not None and original.result is not None
    assert replay.result["runs"] == original.result["runs"]


def test_a_session_without_its_frames_says_they_were_removed(
    finished_job: FinishedJob, tmp_path: Path
) -> None:
    copy = tmp_path / finished_job.path.name
    shutil.copytree(finished_job.path, copy, ignore=shutil.ignore_patterns("frames"))
    s = rigd.Session(copy)
    try:
        s.frames()
    except FileNotFoundError as e:
        assert "frames are gone" in str(e) and "--keep" in str(e)
    else:
        raise AssertionError("frames() of a session without frames/ did not fail")
