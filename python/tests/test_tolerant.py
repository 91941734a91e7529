"""Clients tolerate what a newer daemon may send: unknown event kinds, line types and fields
(a fake daemon on a real Unix socket mixes them into a job's stream)."""

from __future__ import annotations

import asyncio
import json
import socket
import threading
from pathlib import Path
from typing import Any, Iterator

import pytest

import rigd

JOB = 7


def _stream() -> list[dict[str, Any]]:
    ev = {"type": "event", "v": 1, "job_id": JOB}
    return [
        {"type": "telemetry", "v": 1, "load": 0.5},  # a line type no client knows
        {**ev, "event": "accepted", "queue_position": 0, "total_frames": 1, "job": {"steps": 1}, "priority": 3},
        {**ev, "event": "calibrating", "stage": "axis", "nested": {"a": [1, 2]}},  # unknown kind
        {**ev, "event": "started", "session": "s1", "total_frames": 1, "operator": "x"},
        {"type": "reply", "v": 1, "ok": False, "error": {"code": "internal", "message": "this client fell behind and lost 2 events"}},
        {**ev, "event": "step", "index": 0, "run": 0, "case": "scan", "repeat": 0, "commanded_um": 1000.0,
         "axis_um": 1000.0, "interferometer_um": None, "total_frames": 1,
         "timings": {"move_ms": 1.0, "settle_ms": 0.0, "grab_ms": 2.0, "encode_ms": 3.0}, "focus": 0.9},
        {**ev, "job_id": JOB + 1, "event": "step", "index": 0, "run": 0, "case": "scan", "repeat": 0, "commanded_um": 5.0},
        {**ev, "event": "thermal_drift", "drift_um": 0.1},  # unknown kind
        {**ev, "event": "finished", "session": "s1", "checksum": "abc"},
    ]  # fmt: skip


def _serve(server: socket.socket) -> None:
    conn, _ = server.accept()
    f = conn.makefile("rwb")
    try:
        for line in f:
            req = json.loads(line)
            kind, rid = req["kind"], req.get("id")
            out: list[dict[str, Any]] = []
            if kind == "hello":
                result: Any = {"protocol": 1, "rigd": "9.9.9", "future": {"x": 1}}
            elif kind == "subscribe":
                result = {"subscribed": req.get("job_id"), "status": None}
            elif kind == "submit":
                result = {"job_id": JOB, "queue_position": 0, "total_frames": 1, "shiny": True}
                out = _stream()
            elif kind == "result":
                result = {"session": "s1", "state": "finished", "reason": None, "result": {"runs": []}, "extra": 1}
            else:
                result = None
            if result is None:
                reply = {"type": "reply", "v": 1, "id": rid, "ok": False,
                         "error": {"code": "teapot", "message": f"no {kind} here"}}  # fmt: skip
            else:
                reply = {"type": "reply", "v": 1, "id": rid, "ok": True, "result": result}
            for msg in [reply, *out]:
                f.write((json.dumps(msg) + "\n").encode())
            f.flush()
    finally:
        f.close()
        conn.close()


@pytest.fixture
def fake(tmp_path: Path) -> Iterator[Path]:
    path = tmp_path / "fake.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(path))
    server.listen(1)
    t = threading.Thread(target=_serve, args=(server,), daemon=True)
    t.start()
    yield path
    server.close()


def test_sync_client_skips_unknown_kinds_and_fields(fake: Path) -> None:
    with rigd.Client(fake, timeout=10) as c:
        assert c.hello()["rigd"] == "9.9.9"
        c.subscribe()
        job_id = c.submit(steps=1)["job_id"]
        events = []
        for ev in c.events():
            if ev.job_id == job_id:
                events.append(ev)
                if ev.terminal:
                    break
        assert [ev.event for ev in events] == [
            "accepted", "calibrating", "started", "step", "thermal_drift", "finished",
        ]  # fmt: skip
        unknown = [ev for ev in events if isinstance(ev, rigd.UnknownEvent)]
        assert [u.name for u in unknown] == ["calibrating", "thermal_drift"]
        assert unknown[0].raw["nested"] == {"a": [1, 2]}
        step = events[3]
        assert isinstance(step, rigd.Step) and step.interferometer_um is None
        assert step.timings == rigd.Timings(move_ms=1.0, settle_ms=0.0, grab_ms=2.0)
        assert step.raw["focus"] == 0.9
        assert c.notices == ["this client fell behind and lost 2 events"]
        # An error code this package does not know is still an error, with its code.
        with pytest.raises(rigd.RigdError) as e:
            c.request("frobnicate")
        assert e.value.code == "teapot" and type(e.value) is rigd.RigdError


def test_run_ends_on_the_jobs_end_through_unknown_events(fake: Path) -> None:
    with rigd.Client(fake, timeout=10) as c:
        assert c.run(steps=1)["state"] == "finished"


def test_async_client_skips_unknown_kinds_and_fields(fake: Path) -> None:
    async def main() -> list[str]:
        async with await rigd.AsyncClient.connect(fake) as c:
            assert (await c.hello())["future"] == {"x": 1}
            reply = await c.run(steps=1)
            assert reply["state"] == "finished"
            return c.notices

    assert asyncio.run(asyncio.wait_for(main(), 10)) == ["this client fell behind and lost 2 events"]


def test_a_known_event_without_a_required_field_is_an_error() -> None:
    with pytest.raises(rigd.ProtocolError, match="without `session`"):
        rigd.parse_event({"type": "event", "job_id": 1, "event": "finished"})
