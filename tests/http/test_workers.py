"""The guard's worker threads: one loop delivery per batch, the urgent lane first."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from typing import Any

import pytest

from antireplay.http.workers import Workers


def _blocker(started: threading.Event, go: threading.Event) -> Callable[[], str]:
    def block() -> str:
        started.set()
        go.wait(timeout=30)
        return "blocker"

    return block


async def _until(event: threading.Event) -> None:
    """Wait for ``event`` set by a worker, without blocking the loop."""
    await asyncio.to_thread(event.wait, 30)


def test_an_urgent_job_runs_before_every_queued_ordinary_job() -> None:
    """A blocked pool with 20 ordinary jobs queued: the urgent job queued last runs first."""
    workers = Workers(1)
    ran: list[str] = []

    async def scenario() -> None:
        started, go = threading.Event(), threading.Event()
        blocked = workers(_blocker(started, go))
        await _until(started)
        jobs = [workers(ran.append, f"job-{i}") for i in range(20)]
        estop = workers.first(ran.append, "estop")
        await asyncio.sleep(0)  # the iteration's jobs are queued when it ends
        go.set()
        await asyncio.gather(blocked, estop, *jobs)

    try:
        asyncio.run(scenario())
    finally:
        workers.shutdown()
    assert ran == ["estop", *(f"job-{i}" for i in range(20))]


def test_an_urgent_job_preempts_the_rest_of_a_batch_already_taken() -> None:
    """A worker that took a batch of ordinary jobs runs an urgent job queued meanwhile
    right after the job in progress, then the rest of its batch in order."""
    workers = Workers(1, batch=8)
    ran: list[str] = []
    started, go = threading.Event(), threading.Event()

    def first() -> None:
        started.set()
        go.wait(timeout=30)
        ran.append("job-0")

    async def scenario() -> None:
        jobs = [workers(first), *(workers(ran.append, f"job-{i}") for i in range(1, 6))]
        await _until(started)  # the worker holds all six in one batch
        estop = workers.first(ran.append, "estop")
        await asyncio.sleep(0)
        go.set()
        await asyncio.gather(estop, *jobs)

    try:
        asyncio.run(scenario())
    finally:
        workers.shutdown()
    assert ran == ["job-0", "estop", *(f"job-{i}" for i in range(1, 6))]


def test_a_batch_of_results_reaches_the_loop_in_one_delivery_and_errors_raise_there() -> None:
    workers = Workers(1, batch=8)

    def fail() -> None:
        raise ValueError("bad")

    async def scenario() -> list[Any]:
        started, go = threading.Event(), threading.Event()
        blocked = workers(_blocker(started, go))
        await _until(started)
        jobs = [workers(pow, 2, i) for i in range(7)]
        failing = workers(fail)
        await asyncio.sleep(0)
        go.set()
        results = await asyncio.gather(blocked, *jobs)
        with pytest.raises(ValueError, match="bad"):
            await failing
        return results

    try:
        results = asyncio.run(scenario())
    finally:
        workers.shutdown()
    assert results == ["blocker", *(2**i for i in range(7))]
    assert (workers.jobs, workers.deliveries) == (9, 2)  # the blocker's, then the eight's


def test_shutdown_finishes_queued_jobs_and_then_refuses_new_ones() -> None:
    workers = Workers(2)

    async def scenario() -> list[int]:
        return list(await asyncio.gather(*(workers(abs, -i) for i in range(50))))

    assert asyncio.run(scenario()) == list(range(50))
    workers.shutdown()

    async def late() -> None:
        workers(abs, 1)

    with pytest.raises(RuntimeError, match="shut down"):
        asyncio.run(late())


def test_jobs_submitted_as_the_workers_shut_down_fail_instead_of_hanging() -> None:
    workers = Workers(1)

    async def scenario() -> None:
        job = workers(abs, -1)  # queued when this iteration ends: after the shutdown
        workers.shutdown()
        with pytest.raises(RuntimeError, match="shut down"):
            await job

    asyncio.run(scenario())
