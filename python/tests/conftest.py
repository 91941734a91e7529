"""A live `rigd --sim` for the tests: started once on a temporary socket and data root
(`$RIGD_BIN`, default the checkout's target/debug/rigd), terminated at the end."""

from __future__ import annotations

import os
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import pytest

import rigd

REPO = Path(__file__).resolve().parents[2]
#: A small, fast job: 4 frames 50 µm apart, processed at k = 2, no settle.
FAST_JOB: dict[str, Any] = {"step_um": 50, "steps": 4, "k": 2, "settle_ms": 0}


@dataclass
class Daemon:
    socket: Path
    data_root: Path
    proc: subprocess.Popen[bytes]
    log: Path
    capabilities: set[str] | None = field(default=None)

    def client(self) -> rigd.Client:
        return rigd.Client(self.socket, timeout=60)


def rigd_bin() -> Path:
    path = Path(os.environ.get("RIGD_BIN", REPO / "target" / "debug" / "rigd"))
    if not path.is_file():
        pytest.exit(f"no rigd binary at {path}: build it (cargo build --bin rigd) or set RIGD_BIN")
    return path


@pytest.fixture(scope="session")
def daemon() -> Iterator[Daemon]:
    with tempfile.TemporaryDirectory(prefix="rigd-py-") as tmp:
        sock, data, log = Path(tmp) / "rigd.sock", Path(tmp) / "data", Path(tmp) / "rigd.log"
        with open(log, "wb") as out:
            proc = subprocess.Popen(
                [str(rigd_bin()), "--sim", "--socket", str(sock), "--data-root", str(data)],
                stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            )  # fmt: skip
        d = Daemon(sock, data, proc, log)
        try:
            _wait_for(d)
            with d.client() as c:
                d.capabilities = c.capabilities()
            # A daemon from before `hello` capabilities (another branch's build, say):
            # $RIGD_TEST_CAPABILITIES names the request kinds to test anyway.
            assumed = os.environ.get("RIGD_TEST_CAPABILITIES")
            if d.capabilities is None and assumed:
                d.capabilities = {k.strip() for k in assumed.split(",") if k.strip()}
            yield d
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _wait_for(d: Daemon) -> None:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if d.proc.poll() is not None:
            pytest.exit(f"rigd exited ({d.proc.returncode}):\n{d.log.read_text()}")
        if d.socket.exists():
            try:
                with d.client() as c:
                    c.hello()
                return
            except OSError:
                pass
        time.sleep(0.05)
    pytest.exit(f"rigd did not answer on {d.socket} within 60 s:\n{d.log.read_text()}")


@pytest.fixture
def client(daemon: Daemon) -> Iterator[rigd.Client]:
    with daemon.client() as c:
        yield c


@dataclass
class FinishedJob:
    job_id: int
    events: list[rigd.Event]
    reply: dict[str, Any]
    path: Path


@pytest.fixture(scope="session")
def finished_job(daemon: Daemon) -> FinishedJob:
    """One fast processed job, followed from before its submit, and its session folder."""
    with daemon.client() as c:
        c.subscribe()
        job_id = c.submit(FAST_JOB)["job_id"]
        events: list[rigd.Event] = []
        for ev in c.events():
            if ev.job_id == job_id:
                events.append(ev)
                if ev.terminal:
                    break
        reply = c.result(job_id)
    return FinishedJob(job_id, events, reply, daemon.data_root / reply["session"])


def needs(daemon: Daemon, kind: str) -> None:
    """Skip unless the daemon's `hello` lists request `kind` (added on other branches)."""
    if daemon.capabilities is None or kind not in daemon.capabilities:
        pytest.skip(f"this rigd does not serve `{kind}` (hello lists no such capability)")
