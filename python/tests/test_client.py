"""The sync client against the live rigd --sim: requests, events, errors."""

from __future__ import annotations

from pathlib import Path

import pytest

import rigd
from conftest import FAST_JOB, Daemon, FinishedJob


def test_hello_describes_the_sim_rig(client: rigd.Client) -> None:
    hello = client.hello()
    assert hello["protocol"] == 1
    assert hello["rig"]["mode"] == "sim"
    assert hello["rig"]["frame_size"] == [1280, 720]


def test_events_come_in_order(finished_job: FinishedJob) -> None:
    kinds = [ev.kind for ev in finished_job.events]
    assert kinds[:2] == ["accepted", "started"]
    assert kinds[-2:] == ["result", "finished"]
    steps = [ev for ev in finished_job.events if isinstance(ev, rigd.Step)]
    assert [s.index for s in steps] == [0, 1, 2, 3]
    start = steps[0].commanded_um
    assert [s.commanded_um for s in steps] == [start + 50.0 * i for i in range(4)]
    # Each frame is processed, after its step event (it is on disk by then).
    at = {(ev.kind, getattr(ev, "index", None)): n for n, ev in enumerate(finished_job.events)}
    processed = [ev for ev in finished_job.events if isinstance(ev, rigd.Processed)]
    assert sorted(p.index for p in processed) == [0, 1, 2, 3]
    for p in processed:
        assert at[("step", p.index)] < at[("processed", p.index)]
        assert p.targets_found == 12
    started = finished_job.events[1]
    assert isinstance(started, rigd.Started) and started.total_frames == 4
    assert isinstance(finished_job.events[-1], rigd.Finished)
    assert finished_job.events[-1].session == started.session
    assert all(s.timings is not None and s.timings.move_ms >= 0 for s in steps)


def test_run_returns_the_result(client: rigd.Client) -> None:
    reply = client.run(FAST_JOB, label="python run")
    assert reply["state"] == "finished"
    runs = reply["result"]["runs"]
    assert len(runs) == 1 and runs[0]["k"] == 2 and runs[0]["frames"] == 4
    assert len(runs[0]["result"]["objects"]) == 12
    # A second run on the same client does not double its events.
    again = client.run(FAST_JOB, process=False)
    assert again["state"] == "finished" and again["session"] != reply["session"]


def test_watch_follows_a_job_to_its_end(client: rigd.Client, daemon: Daemon) -> None:
    with daemon.client() as other:
        job_id = other.submit(step_um=100, steps=3, settle_ms=0, process=False)["job_id"]
    events = list(client.watch(job_id))
    assert events and isinstance(events[-1], rigd.Finished)
    assert all(ev.job_id == job_id for ev in events)
    indices = [ev.index for ev in events if isinstance(ev, rigd.Step)]
    assert indices == sorted(indices) and set(indices) <= {0, 1, 2}
    # The job has ended: watching it again yields nothing and returns.
    assert list(client.watch(job_id)) == []
    assert client.status(job_id)["state"] == "finished"


def test_errors_carry_the_wire_code(client: rigd.Client) -> None:
    with pytest.raises(rigd.Rejected) as e:
        client.submit(step_um=0, steps=3)
    assert e.value.code == "rejected" and "step" in e.value.message
    with pytest.raises(rigd.BadRequest) as b:
        client.submit(step_um=50, steps=3, stepz=1)
    assert b.value.code == "bad_request" and "stepz" in b.value.message
    with pytest.raises(rigd.NotFound) as n:
        client.result(987654)
    assert n.value.code == "not_found"
    with pytest.raises(rigd.BadRequest):
        client.request("no_such_request")
    with pytest.raises(rigd.Rejected):
        client.run(step_um=50, steps=200000)  # too many frames: refused at submit
    # The connection keeps serving after errors.
    assert client.hello()["protocol"] == 1


def test_a_cancelled_job_raises_job_failed(client: rigd.Client, daemon: Daemon) -> None:
    client.subscribe()
    job_id = client.submit(step_um=50, steps=40, settle_ms=200, process=False)["job_id"]
    with daemon.client() as other:
        for ev in client.events():
            if isinstance(ev, rigd.Step) and ev.job_id == job_id:
                assert other.cancel(job_id)["state"] == "cancelling"
                break
    end = next(ev for ev in client.events() if ev.job_id == job_id and ev.terminal)
    assert isinstance(end, rigd.Cancelled)
    assert end.reason is not None and "cancelled by a client" in end.reason
    assert end.detail is not None and end.detail["kind"] == "cancelled"


def test_list_follows_every_page(client: rigd.Client) -> None:
    for _ in range(3):
        client.run(step_um=50, steps=1, settle_ms=0, process=False)
    everything = client.list(limit=1000)
    assert everything["next_before"] is None
    pages = list(client.pages(limit=1))
    assert len(pages) >= 3
    paged = [s["job_id"] for p in pages for s in p["sessions"]]
    assert paged == [s["job_id"] for s in everything["sessions"]]
    assert paged == sorted(paged, reverse=True) and len(set(paged)) == len(paged)
    assert [j["job_id"] for j in client.jobs(limit=2)] == [j["job_id"] for j in everything["jobs"]]
    assert [s["name"] for s in client.sessions(limit=2)] == [s["name"] for s in everything["sessions"]]


def test_status_without_a_job(client: rigd.Client) -> None:
    status = client.status()
    assert "running" in status and "queued" in status
    assert status["rig_state"]["state"] in ("ready", "busy")


def test_socket_path_as_rigctl_resolves_it(
    monkeypatch: pytest.MonkeyPatch, daemon: Daemon, tmp_path: Path
) -> None:
    import os

    monkeypatch.setenv("RIGD_SOCKET", str(daemon.socket))
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    assert rigd.default_socket() == daemon.socket
    with rigd.Client() as c:  # no path: $RIGD_SOCKET
        assert c.hello()["protocol"] == 1
    monkeypatch.delenv("RIGD_SOCKET")
    assert rigd.default_socket() == tmp_path / "rigd.sock"
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert rigd.default_socket() == Path(f"/tmp/rigd-{os.getuid()}.sock")


def test_no_daemon_at_the_socket_names_it_and_says_what_to_do(tmp_path: Path) -> None:
    missing = tmp_path / "missing.sock"
    with pytest.raises(rigd.CannotConnect) as e:
        rigd.Client(missing)
    text = str(e.value)
    assert str(missing) in text and "is it running?" in text and "RIGD_SOCKET" in text
    assert isinstance(e.value, ConnectionError) and e.value.path == missing
