"""The synchronous client: one Unix-socket connection to rigd, JSON lines each way."""

from __future__ import annotations

import builtins
import os
import socket
from collections import deque
from typing import Any, Iterator, Mapping, Optional

from .errors import CannotConnect, ConnectionClosed, JobFailed, error_from_wire
from .events import Event, parse_event
from .paths import resolve_socket
from .wire import ENDED_STATES, OWN_IDLESS_CODES, Json, decode_line, encode_request, notice_of


class Client:
    """A connection to rigd. `Client()` connects to the socket rigctl would use
    (`$RIGD_SOCKET`, `$XDG_RUNTIME_DIR/rigd.sock`, `/tmp/rigd-UID.sock`).

    Events that arrive while a reply is awaited are kept for `events()` / `watch()`.
    Id-less notices (events lost by a slow reader) are collected in `notices`.
    """

    def __init__(
        self, path: str | os.PathLike[str] | None = None, *, timeout: Optional[float] = None
    ) -> None:
        self.path = resolve_socket(path)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout)
        try:
            self._sock.connect(str(self.path))
        except OSError as e:
            self._sock.close()
            raise CannotConnect(self.path, e) from e
        self._file = self._sock.makefile("rwb")
        self._next_id = 1
        self._pending: deque[Event] = deque()
        self._all = False  # subscribed to every job's events
        self.notices: list[str] = []

    # -- the connection ---------------------------------------------------------------

    def close(self) -> None:
        self._file.close()
        self._sock.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _read(self) -> Json:
        line = self._file.readline()
        if not line:
            raise ConnectionClosed("rigd closed the connection")
        return decode_line(line)

    def send_line(self, line: bytes) -> None:
        """Write one raw line (for tests of the daemon's refusals)."""
        self._file.write(line)
        self._file.flush()

    def request(self, kind: str, **fields: Any) -> Json:
        """Send a request of `kind`; return its `result`, or raise the daemon's error as a
        `RigdError` (`code`, `message`). Fields given as None are left out."""
        rid = self._next_id
        self._next_id += 1
        self.send_line(encode_request(rid, kind, fields))
        while True:
            msg = self._read()
            kind_of = msg.get("type")
            if kind_of == "event":
                self._pending.append(parse_event(msg))
                continue
            if kind_of != "reply":
                continue  # a line type this client does not know
            if "id" not in msg:
                err = msg.get("error")
                if isinstance(err, dict) and err.get("code") in OWN_IDLESS_CODES:
                    raise error_from_wire(err)
                self.notices.append(notice_of(msg))
                continue
            if msg.get("id") != rid:
                continue
            if msg.get("ok"):
                result = msg.get("result")
                return result if isinstance(result, dict) else {"value": result}
            raise error_from_wire(msg.get("error"))

    def next_event(self) -> Event:
        """The next event of this connection's subscriptions (blocks)."""
        if self._pending:
            return self._pending.popleft()
        while True:
            msg = self._read()
            if msg.get("type") == "event":
                return parse_event(msg)
            if msg.get("type") == "reply" and "id" not in msg:
                self.notices.append(notice_of(msg))

    def events(self) -> Iterator[Event]:
        """Every event of this connection's subscriptions, as they come (endless)."""
        while True:
            yield self.next_event()

    # -- requests -----------------------------------------------------------------------

    def hello(self) -> Json:
        return self.request("hello")

    def capabilities(self) -> Optional[set[str]]:
        """The request kinds the daemon serves (`hello`'s `capabilities.requests`), or None
        from a daemon that predates capabilities."""
        caps = self.hello().get("capabilities")
        if isinstance(caps, dict) and isinstance(caps.get("requests"), list):
            return {str(k) for k in caps["requests"]}
        return None

    def submit(self, job: Optional[Mapping[str, Any]] = None, **job_fields: Any) -> Json:
        """Queue a job (`{"step_um": 50, "steps": 4, "k": 2}` or keywords): `job_id`,
        `queue_position`, `total_frames`, `job` (as it will run)."""
        return self.request("submit", job={**(job or {}), **job_fields})

    def status(self, job_id: Optional[int] = None) -> Json:
        return self.request("status", job_id=job_id)

    def list(self, limit: Optional[int] = None, before: Optional[int] = None) -> Json:
        """One page of `list` (newest first); `next_before` says where the next starts."""
        return self.request("list", limit=limit, before=before)

    def pages(self, limit: Optional[int] = None) -> Iterator[Json]:
        """Every page of `list`, following `next_before`."""
        before: Optional[int] = None
        while True:
            page = self.list(limit=limit, before=before)
            yield page
            before = page.get("next_before")
            if before is None:
                return

    def jobs(self, limit: Optional[int] = None) -> builtins.list[Json]:
        """Every job this daemon run knows, newest first (all pages)."""
        return [j for p in self.pages(limit) for j in p.get("jobs", [])]

    def sessions(self, limit: Optional[int] = None) -> builtins.list[Json]:
        """Every session on disk, newest first (all pages)."""
        return [s for p in self.pages(limit) for s in p.get("sessions", [])]

    def cancel(self, job_id: int) -> Json:
        return self.request("cancel", job_id=job_id)

    def result(self, job_id: int) -> Json:
        """`session`, `state`, `reason`, `result` (the session's result.json)."""
        return self.request("result", job_id=job_id)

    def subscribe(self, job_id: Optional[int] = None) -> Json:
        """Follow one job's events, or every job's; read them with `events()`."""
        reply = self.request("subscribe", job_id=job_id)
        self._all = self._all or job_id is None
        return reply

    def replay(self, session: str, **processing: Any) -> Json:
        return self.request("replay", session=session, processing=processing or None)

    def resume_session(self, session: str) -> Json:
        """Queue a new job that takes an interrupted (incomplete, failed or cancelled)
        session's plan on from its first missing frame. The reply is a submit's, with
        `resumed_from` (`session`, `first_index`); `total_frames` counts the whole plan."""
        return self.request("resume_session", session=session)

    def unlock(self, stage: Optional[str] = None) -> Json:
        return self.request("unlock", stage=stage)

    def home(self, stage: Optional[str] = None) -> Json:
        return self.request("home", stage=stage)

    def reconnect(self, stage: Optional[str] = None) -> Json:
        return self.request("reconnect", stage=stage)

    # Manual control (docs/protocol.md: position, move, stop, pause, resume).
    def position(self) -> Json:
        return self.request("position")

    def move(
        self, stage: str, *, to_um: Optional[float] = None, by_um: Optional[float] = None
    ) -> Json:
        return self.request("move", stage=stage, to_um=to_um, by_um=by_um)

    def stop(self) -> Json:
        return self.request("stop")

    def pause(self, job_id: int) -> Json:
        return self.request("pause", job_id=job_id)

    def resume(self, job_id: int) -> Json:
        return self.request("resume", job_id=job_id)

    # Live view (snap, preview, preview_stop).
    def snap(
        self, *, scale: Optional[float] = None, crop: Optional[tuple[int, int, int, int]] = None
    ) -> Json:
        return self.request("snap", scale=scale, crop=list(crop) if crop else None)

    def preview(
        self,
        max_fps: float,
        *,
        scale: Optional[float] = None,
        crop: Optional[tuple[int, int, int, int]] = None,
    ) -> Json:
        return self.request(
            "preview", max_fps=max_fps, scale=scale, crop=list(crop) if crop else None
        )

    def preview_stop(self) -> Json:
        return self.request("preview_stop")

    # -- following jobs -------------------------------------------------------------------

    def watch(self, job_id: int) -> Iterator[Event]:
        """Subscribe to `job_id` and yield its events up to and including its last one
        (`finished`, `failed` or `cancelled`). Nothing if the job has already ended."""
        # Already subscribed to every job: a second subscription would double the events.
        status = self.status(job_id) if self._all else self.subscribe(job_id).get("status")
        if isinstance(status, dict) and status.get("state") in ENDED_STATES:
            return
        yield from self._follow(job_id)

    def _follow(self, job_id: int) -> Iterator[Event]:
        while True:
            ev = self.next_event()
            if ev.job_id != job_id:
                continue
            yield ev
            if ev.terminal:
                return

    def run(self, job: Optional[Mapping[str, Any]] = None, **job_fields: Any) -> Json:
        """Submit a job, follow it to its end and return its `result` reply (`session`,
        `state`, `reason`, `result`). Raises `JobFailed` if it ends failed or cancelled.

        Subscribes to every job first, so none of the new job's events can be missed;
        other jobs' events met meanwhile are dropped.
        """
        if not self._all:
            self.subscribe()
        job_id = int(self.submit(job, **job_fields)["job_id"])
        last: Optional[Event] = None
        for last in self._follow(job_id):
            pass
        if last is None or last.kind != "finished":
            raise JobFailed(job_id, last)
        return self.result(job_id)


def connect(path: str | os.PathLike[str] | None = None, *, timeout: Optional[float] = None) -> Client:
    """`Client(path)`."""
    return Client(path, timeout=timeout)
