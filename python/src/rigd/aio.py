"""The asyncio client: one connection, a reader task that hands replies to the requests
awaiting them (by id) and events to the iterators following them, so requests and
`async for ev in client.watch(job)` can run side by side in one connection."""

from __future__ import annotations

import asyncio
import os
from typing import Any, AsyncIterator, Mapping, Optional

from .errors import (
    CannotConnect,
    ConnectionClosed,
    JobFailed,
    ProtocolError,
    RigdError,
    error_from_wire,
)
from .events import Event, parse_event
from .paths import resolve_socket
from .wire import ENDED_STATES, OWN_IDLESS_CODES, Json, decode_line, encode_request, notice_of

#: Longest line read: a live-view frame carries a base64 PNG.
LINE_LIMIT = 64 * 1024 * 1024

_Queue = asyncio.Queue[Optional[Event]]


class AsyncClient:
    """`client = await AsyncClient.connect(path)` (or `async with await ...`)."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._reader = reader
        self._writer = writer
        self._next_id = 1
        self._replies: dict[int, asyncio.Future[Json]] = {}
        self._queues: list[tuple[Optional[int], _Queue]] = []
        self._all = False
        # Every job's events from `subscribe()` on, for `events()` (none lost meanwhile).
        self._sub_q: Optional[_Queue] = None
        self._closed: Optional[BaseException] = None
        self.notices: list[str] = []
        self._task = asyncio.get_running_loop().create_task(self._read_loop())

    @classmethod
    async def connect(cls, path: str | os.PathLike[str] | None = None) -> "AsyncClient":
        where = resolve_socket(path)
        try:
            reader, writer = await asyncio.open_unix_connection(str(where), limit=LINE_LIMIT)
        except OSError as e:
            raise CannotConnect(where, e) from e
        return cls(reader, writer)

    async def close(self) -> None:
        self._writer.close()
        try:
            await self._writer.wait_closed()
        except OSError:
            pass
        self._task.cancel()
        try:
            await self._task
        except (asyncio.CancelledError, Exception):
            pass

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- the reader task ----------------------------------------------------------------

    async def _read_loop(self) -> None:
        err: BaseException = ConnectionClosed("rigd closed the connection")
        try:
            while True:
                line = await self._reader.readline()
                if not line:
                    break
                self._dispatch(decode_line(line))
        except (ProtocolError, OSError, ValueError) as e:
            err = e
        finally:
            self._closed = err
            for fut in self._replies.values():
                if not fut.done():
                    fut.set_exception(err)
            for _, q in self._queues:
                q.put_nowait(None)

    def _dispatch(self, msg: Json) -> None:
        if msg.get("type") == "event":
            ev = parse_event(msg)
            for job_id, q in self._queues:
                if job_id is None or job_id == ev.job_id:
                    q.put_nowait(ev)
        elif msg.get("type") == "reply":
            self._reply(msg)

    def _reply(self, msg: Json) -> None:
        rid = msg.get("id")
        if rid is None:
            err = msg.get("error")
            own = isinstance(err, dict) and err.get("code") in OWN_IDLESS_CODES
            if own and self._replies:
                rid = min(self._replies)  # the oldest request the daemon could not read
            else:
                self.notices.append(notice_of(msg))
                return
        fut = self._replies.pop(rid, None) if isinstance(rid, int) else None
        if fut is None or fut.done():
            return
        if msg.get("ok"):
            result = msg.get("result")
            fut.set_result(result if isinstance(result, dict) else {"value": result})
        else:
            fut.set_exception(error_from_wire(msg.get("error")))

    # -- requests -----------------------------------------------------------------------

    async def request(self, kind: str, **fields: Any) -> Json:
        """Send a request; its `result`, or the daemon's error raised as a `RigdError`."""
        if self._closed is not None:
            raise ConnectionClosed(str(self._closed))
        rid = self._next_id
        self._next_id += 1
        fut: asyncio.Future[Json] = asyncio.get_running_loop().create_future()
        self._replies[rid] = fut
        self._writer.write(encode_request(rid, kind, fields))
        await self._writer.drain()
        return await fut

    async def hello(self) -> Json:
        return await self.request("hello")

    async def submit(self, job: Optional[Mapping[str, Any]] = None, **job_fields: Any) -> Json:
        return await self.request("submit", job={**(job or {}), **job_fields})

    async def status(self, job_id: Optional[int] = None) -> Json:
        return await self.request("status", job_id=job_id)

    async def list(self, limit: Optional[int] = None, before: Optional[int] = None) -> Json:
        return await self.request("list", limit=limit, before=before)

    async def pages(self, limit: Optional[int] = None) -> AsyncIterator[Json]:
        """Every page of `list`, following `next_before`."""
        before: Optional[int] = None
        while True:
            page = await self.list(limit=limit, before=before)
            yield page
            before = page.get("next_before")
            if before is None:
                return

    async def cancel(self, job_id: int) -> Json:
        return await self.request("cancel", job_id=job_id)

    async def result(self, job_id: int) -> Json:
        return await self.request("result", job_id=job_id)

    async def subscribe(self, job_id: Optional[int] = None) -> Json:
        """Follow one job's events, or every job's; `events()` yields every event from
        here on (none is lost before it is read)."""
        if self._sub_q is None:
            self._sub_q = asyncio.Queue()
            self._queues.append((None, self._sub_q))
        return await self._subscribe(job_id)

    async def _subscribe(self, job_id: Optional[int]) -> Json:
        reply = await self.request("subscribe", job_id=job_id)
        self._all = self._all or job_id is None
        return reply

    async def position(self) -> Json:
        return await self.request("position")

    async def move(
        self, stage: str, *, to_um: Optional[float] = None, by_um: Optional[float] = None
    ) -> Json:
        return await self.request("move", stage=stage, to_um=to_um, by_um=by_um)

    async def stop(self) -> Json:
        return await self.request("stop")

    async def pause(self, job_id: int) -> Json:
        return await self.request("pause", job_id=job_id)

    async def resume(self, job_id: int) -> Json:
        return await self.request("resume", job_id=job_id)

    async def resume_session(self, session: str) -> Json:
        """As `Client.resume_session`."""
        return await self.request("resume_session", session=session)

    async def snap(
        self, *, scale: Optional[float] = None, crop: Optional[tuple[int, int, int, int]] = None
    ) -> Json:
        return await self.request("snap", scale=scale, crop=list(crop) if crop else None)

    # -- following jobs -------------------------------------------------------------------

    async def _drain(
        self, q: _Queue, job_id: Optional[int], keep: bool = False
    ) -> AsyncIterator[Event]:
        try:
            while True:
                ev = await q.get()
                if ev is None:
                    raise ConnectionClosed(str(self._closed))
                yield ev
                if job_id is not None and ev.terminal:
                    return
        finally:
            if not keep:
                self._queues = [(j, x) for j, x in self._queues if x is not q]

    async def events(self) -> AsyncIterator[Event]:
        """Every event of this connection's subscriptions since `subscribe()` (endless).
        Breaking out of the loop and calling it again goes on where it stopped."""
        if self._sub_q is None:
            self._sub_q = asyncio.Queue()
            self._queues.append((None, self._sub_q))
        async for ev in self._drain(self._sub_q, None, keep=True):
            yield ev

    async def watch(self, job_id: int) -> AsyncIterator[Event]:
        """Subscribe to `job_id` and yield its events up to and including its last one."""
        q: _Queue = asyncio.Queue()
        self._queues.append((job_id, q))  # before subscribing: no event can slip past
        status: Any
        try:
            if self._all:
                status = await self.status(job_id)
            else:
                status = (await self._subscribe(job_id)).get("status")
        except RigdError:
            self._queues = [(j, x) for j, x in self._queues if x is not q]
            raise
        if isinstance(status, dict) and status.get("state") in ENDED_STATES and q.empty():
            self._queues = [(j, x) for j, x in self._queues if x is not q]
            return
        async for ev in self._drain(q, job_id):
            yield ev

    async def run(self, job: Optional[Mapping[str, Any]] = None, **job_fields: Any) -> Json:
        """Submit, follow to the end, return the `result` reply (`JobFailed` if it ends
        failed or cancelled)."""
        q: _Queue = asyncio.Queue()
        self._queues.append((None, q))
        try:
            if not self._all:
                await self._subscribe(None)
            job_id = int((await self.submit(job, **job_fields))["job_id"])
            last: Optional[Event] = None
            async for ev in self._drain(q, None):
                if ev.job_id == job_id:
                    last = ev
                    if ev.terminal:
                        break
        finally:
            self._queues = [(j, x) for j, x in self._queues if x is not q]
        if last is None or last.kind != "finished":
            raise JobFailed(job_id, last)
        return await self.result(job_id)


async def connect(path: str | os.PathLike[str] | None = None) -> AsyncClient:
    """`await AsyncClient.connect(path)`."""
    return await AsyncClient.connect(path)
