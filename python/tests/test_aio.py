"""The asyncio client against the live rigd --sim."""

from __future__ import annotations

import asyncio
from typing import Any, Coroutine, TypeVar

import pytest

import rigd
from conftest import FAST_JOB, Daemon

T = TypeVar("T")


def arun(coro: Coroutine[Any, Any, T]) -> T:
    return asyncio.run(asyncio.wait_for(coro, 60))


def test_async_run_returns_the_result(daemon: Daemon) -> None:
    async def main() -> dict[str, Any]:
        async with await rigd.AsyncClient.connect(daemon.socket) as c:
            return await c.run(FAST_JOB)

    reply = arun(main())
    assert reply["state"] == "finished"
    assert len(reply["result"]["runs"][0]["result"]["objects"]) == 12


def test_async_watch_while_requests_go_on(daemon: Daemon) -> None:
    async def main() -> tuple[list[rigd.Event], list[str]]:
        async with await rigd.AsyncClient.connect(daemon.socket) as c:
            job = await c.submit(step_um=50, steps=5, settle_ms=20, process=False)
            events: list[rigd.Event] = []
            states: list[str] = []

            async def follow() -> None:
                async for ev in c.watch(job["job_id"]):
                    events.append(ev)

            task = asyncio.create_task(follow())
            while not task.done():  # requests on the same connection meanwhile
                states.append((await c.status(job["job_id"]))["state"])
                await asyncio.sleep(0.02)
            await task
            return events, states

    events, states = arun(main())
    assert isinstance(events[-1], rigd.Finished)
    steps = [ev.index for ev in events if isinstance(ev, rigd.Step)]
    assert steps == sorted(steps) and len(steps) >= 1
    assert set(states) <= {"queued", "running", "finished"}


def test_async_errors_carry_the_wire_code(daemon: Daemon) -> None:
    async def main() -> None:
        async with await rigd.AsyncClient.connect(daemon.socket) as c:
            with pytest.raises(rigd.Rejected) as e:
                await c.submit(step_um=0, steps=3)
            assert e.value.code == "rejected"
            with pytest.raises(rigd.NotFound):
                await c.cancel(987654)
            pages = [p async for p in c.pages(limit=1)]
            assert pages[-1]["next_before"] is None
            assert (await c.hello())["protocol"] == 1

    arun(main())


def test_async_events_of_a_job_from_its_submit(daemon: Daemon) -> None:
    async def main() -> list[rigd.Event]:
        async with await rigd.AsyncClient.connect(daemon.socket) as c:
            await c.subscribe()
            job_id = (await c.submit(step_um=50, steps=2, settle_ms=0, process=False))["job_id"]
            await asyncio.sleep(0.5)  # events arrive before anyone reads: none is lost
            events: list[rigd.Event] = []
            async for ev in c.events():
                if ev.job_id == job_id:
                    events.append(ev)
                    if ev.terminal:
                        break
            # A later job on the same subscription, through a second events() loop.
            second = (await c.submit(step_um=50, steps=1, settle_ms=0, process=False))["job_id"]
            async for ev in c.events():
                if ev.job_id == second and ev.terminal:
                    break
            return events

    events = arun(main())
    kinds = [ev.kind for ev in events]
    assert kinds == ["accepted", "started", "calibration", "step", "step", "finished"]
    # No calibration in a fresh data root: the event says so and why.
    cal = events[2]
    assert isinstance(cal, rigd.Calibration) and not cal.applied, cal
    assert cal.reason and "no current calibration" in cal.reason, cal
