"""The guard's worker threads: one loop delivery per batch, the urgent lane first; the door."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from typing import Any

import pytest

from antireplay.core.clock import ManualClock
from antireplay.http.workers import Door, Workers


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


def test_an_urgent_job_is_queued_at_once_not_when_the_loop_iteration_ends() -> None:
    """The loop blocks right after submitting (as a busy flood iteration does): an urgent
    job runs meanwhile; an ordinary one waits for the iteration's end."""
    workers = Workers(1)
    urgent_ran, ordinary_ran = threading.Event(), threading.Event()

    async def scenario() -> tuple[bool, bool]:
        urgent = workers.first(urgent_ran.set)
        ordinary = workers(ordinary_ran.set)
        during = urgent_ran.wait(timeout=10), ordinary_ran.wait(timeout=0.2)  # loop blocked
        await asyncio.gather(urgent, ordinary)
        return during

    try:
        assert asyncio.run(scenario()) == (True, False)
    finally:
        workers.shutdown()


async def _holding(door: Door, release: asyncio.Event) -> None:
    door.hold()
    await release.wait()
    door.release()


def test_requests_wait_at_a_held_door_until_its_last_holder_lets_go() -> None:
    door = Door()

    async def scenario() -> list[int]:
        first, second = asyncio.Event(), asyncio.Event()
        holders = [asyncio.create_task(_holding(door, e)) for e in (first, second)]
        await asyncio.sleep(0)
        entrant = asyncio.create_task(door.enter())
        seen = []
        for release in (first, second):
            for _ in range(5):
                await asyncio.sleep(0)
            seen.append(int(entrant.done()))
            release.set()
        await asyncio.wait_for(entrant, 5)
        await asyncio.gather(*holders)
        return seen

    assert asyncio.run(scenario()) == [0, 0]
    assert (door.waited, door.timeouts, door.holders) == (1, 0, set())


def test_a_door_never_let_go_lets_requests_in_after_hold_s() -> None:
    door = Door(hold_s=0.01)

    async def scenario() -> None:
        door.hold()  # and never released: a stuck ESTOP cannot stall the gateway
        await asyncio.wait_for(door.enter(), 5)
        await asyncio.wait_for(door.enter(), 5)

    asyncio.run(scenario())
    assert (door.waited, door.timeouts) == (2, 2)


def test_holds_before_the_signature_check_are_bounded_by_their_budget() -> None:
    """What a flood of forged SAFETY messages can hold: ``early_burst``, then
    ``early_per_s``; a holder asking again takes nothing."""
    clock = ManualClock(wall=1_800_000_000.0)
    door = Door(early_per_s=1.0, early_burst=2.0, clock=clock)

    async def early() -> tuple[bool, bool]:
        taken = door.hold_early()
        again = door.hold_early()
        door.release()
        return taken, again

    async def scenario() -> list[tuple[bool, bool]]:
        got = [await asyncio.create_task(early()) for _ in range(3)]
        clock.advance(1.0)
        return [*got, await asyncio.create_task(early())]

    assert asyncio.run(scenario()) == [(True, False), (True, False), (False, False), (True, False)]


def test_copies_of_an_estop_in_flight_or_delivered_hold_no_door() -> None:
    """One hold per ESTOP, not per copy: while E1's request holds the door, its copies take
    none; once E1 is delivered its copies take none either; a new ESTOP holds it."""
    door = Door()

    async def copy(msg_id: str) -> tuple[bool, bool]:
        early = door.hold_early(msg_id)  # claimed before the signature check: E1 is known
        return early, door.hold(msg_id)

    async def scenario() -> list[object]:
        go = asyncio.Event()

        async def original() -> None:
            assert door.hold("E1")
            await go.wait()
            door.release()

        held = asyncio.create_task(original())
        await asyncio.sleep(0)
        in_flight = [await asyncio.create_task(copy("E1")) for _ in range(8)]
        holders = len(door.holders)
        go.set()
        await held
        delivered = await asyncio.create_task(copy("E1"))
        opened = door._opened is None
        new = await asyncio.create_task(copy("E2"))
        return [in_flight, holders, delivered, opened, new]

    in_flight, holders, delivered, opened, new = asyncio.run(scenario())
    assert in_flight == [(False, False)] * 8 and holders == 1
    assert delivered == (False, False) and opened
    assert new == (False, True)  # the copies spent the early budget: held once authenticated
    assert (door.holds, door.copies) == (2, 9)


def test_a_copy_before_its_signature_check_spends_the_early_budget() -> None:
    """Copies count against the early budget: with a burst of 2, one copy leaves one early
    hold for a new SAFETY message, then none."""
    clock = ManualClock(wall=1_800_000_000.0)
    door = Door(early_per_s=1.0, early_burst=2.0, clock=clock)

    async def scenario() -> list[bool]:
        async def deliver() -> None:
            door.hold("E1")
            door.release()

        await asyncio.create_task(deliver())

        async def early(msg_id: str) -> bool:
            taken = door.hold_early(msg_id)
            if taken:
                door.release()
            return taken

        return [await asyncio.create_task(early(m)) for m in ("E1", "E2", "E3")]

    assert asyncio.run(scenario()) == [False, True, False]


def test_a_copy_arriving_at_a_door_a_new_estop_holds_does_not_hold_it_longer() -> None:
    """The door opens when the new ESTOP is answered, whatever copies of an old one do."""
    door = Door()

    async def scenario() -> bool:
        async def delivered() -> None:
            door.hold("old")
            door.release()

        await asyncio.create_task(delivered())
        go = asyncio.Event()

        async def new() -> None:
            door.hold("new")
            await go.wait()
            door.release()

        async def copy() -> None:
            door.hold_early("old")
            door.hold("old")
            await asyncio.Event().wait()  # the robot never answers the copy

        held = asyncio.create_task(new())
        copies = [asyncio.create_task(copy()) for _ in range(8)]
        await asyncio.sleep(0)
        go.set()
        await held
        opened = door._opened is None
        for task in copies:
            task.cancel()
        return opened

    assert asyncio.run(scenario())
