"""The event-loop driver: junk and known replays refused on the loop, a thread handed at
most one job (a fresh ESTOP's in the urgent lane), the same rules as the thread driver."""

from __future__ import annotations

import asyncio
import concurrent.futures
from collections.abc import Callable
from pathlib import Path
from typing import Any

from antireplay import ManualClock, SecurityConfig
from antireplay.audit import AuditLog, verify
from antireplay.rcan.receive import Outcome, Receiver
from harness import fresh_receiver
from harness.envelopes import registry, signed
from harness.stores import sqlite_store


class _NoThreads(concurrent.futures.ThreadPoolExecutor):
    """A default executor that refuses work: any hand-off but the given offload fails."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Any:
        raise AssertionError(f"{fn!r} went to the loop's default executor")


def test_the_event_loop_driver_hands_work_only_to_its_offload_and_keeps_the_estop_rule(
    receiver: Receiver,
) -> None:
    """On a loop, with the audit trail closed: an ESTOP is delivered flagged, anything else
    is refused 503, as on a thread; every thread hand-off goes through ``offload``."""
    assert receiver.audit is not None
    receiver.audit.close()
    handed: list[Callable[..., Any]] = []

    async def offload(fn: Callable[..., Any], *args: Any) -> Any:
        handed.append(fn)
        return fn(*args)

    async def scenario() -> tuple[Outcome, Outcome]:
        asyncio.get_running_loop().set_default_executor(_NoThreads(1))
        estop = signed(type=6, safety_event="ESTOP", cmd="estop")
        return (
            await receiver.receive_async(estop, None, offload),
            await receiver.receive_async(signed(), None, offload),
        )

    estop, other = asyncio.run(scenario())
    assert (estop.accepted, estop.warning) == (True, "AUDIT_UNAVAILABLE")
    assert (other.accepted, other.status, other.code) == (False, 503, "STATE_UNAVAILABLE")
    assert len(handed) >= 4  # each: its steps 1-6 and its commit; the 503's settle


def test_the_event_loop_driver_hands_a_thread_one_job_at_most_and_safety_the_urgent_lane(
    receiver: Receiver,
) -> None:
    """Junk, a byte-identical copy and a known replay (new bytes, spent msg_id) are refused
    on the loop with no hand-off; a command's signature is one ordinary job; a fresh
    ESTOP's is the urgent lane's."""
    signatures: list[str] = []  # the lane each signature check was handed to

    def lane(name: str) -> Callable[..., Any]:
        async def run(fn: Callable[..., Any], *args: Any) -> Any:
            if getattr(fn, "__name__", "") == "authenticate":
                signatures.append(name)
            return fn(*args)

        return run

    command, estop = signed(msg_id="m-1"), signed(type=6, safety_event="ESTOP", cmd="estop")
    bodies = [b"{not json", command, command, signed(msg_id="m-1", cmd="turn"), estop]

    async def scenario() -> list[Outcome]:
        asyncio.get_running_loop().set_default_executor(_NoThreads(1))
        ordinary, urgent = lane("ordinary"), lane("urgent")
        return [await receiver.receive_async(raw, None, ordinary, urgent) for raw in bodies]

    outcomes = asyncio.run(scenario())
    assert [(o.accepted, o.code) for o in outcomes] == [
        (False, "INVALID_ENVELOPE"), (True, None), (False, "REPLAY_DETECTED"),
        (False, "REPLAY_DETECTED"), (True, None),
    ]  # fmt: skip
    assert signatures == ["ordinary", "urgent"]


def test_an_accepted_command_on_a_loop_is_one_durable_trip_with_the_thread_drivers_row(
    tmp_path: Path, clock: ManualClock
) -> None:
    """With the trail's outbox in the SQLite store, an accepted command's entry and row are
    ONE committer operation (two before: the entry, then the row); its row is the one the
    thread driver writes; a racer that loses the commit gets its refusal row, not the
    accepted one; an ESTOP still takes its two bounded steps."""
    store = sqlite_store(tmp_path / "state.db", clock=clock)
    audit = AuditLog(tmp_path / "audit.db", clock=clock)
    audit.attach(store.outbox())
    receiver = fresh_receiver(SecurityConfig(), registry(), store, audit, clock)
    committer = store.group_commit

    async def offload(fn: Callable[..., Any], *args: Any) -> Any:
        return fn(*args)

    async def scenario() -> list[Outcome]:
        before = committer.operations
        first = await receiver.receive_async(signed(msg_id="loop-1"), None, offload)
        assert committer.operations - before == 1  # the entry and its row: one operation
        twins = [signed(msg_id="twin", cmd=c) for c in ("a", "b")]  # both pass the check
        raced = await asyncio.gather(*(receiver.receive_async(t, None, offload) for t in twins))
        before = committer.operations
        estop = signed(type=6, safety_event="ESTOP", cmd="estop")
        stopped = await receiver.receive_async(estop, None, offload, offload)
        assert committer.operations - before == 2  # its entry, then its row (spillable)
        return [first, *raced, stopped]

    outcomes = asyncio.run(scenario())
    assert receiver.receive(signed(msg_id="thread-1")).accepted
    assert [(o.accepted, o.code) for o in outcomes] in (
        [(True, None), (True, None), (False, "REPLAY_DETECTED"), (True, None)],
        [(True, None), (False, "REPLAY_DETECTED"), (True, None), (True, None)],
    )
    receiver.close()
    rows = {r.msg_id: r for r in AuditLog(tmp_path / "audit.db").tail(20)}
    loop_row, thread_row = rows["loop-1"], rows["thread-1"]
    fields = ("outcome", "code", "warning", "msg_type", "sender", "sender_verified")
    assert [getattr(loop_row, f) for f in fields] == [getattr(thread_row, f) for f in fields]
    twin = [r for r in AuditLog(tmp_path / "audit.db").tail(20) if r.msg_id == "twin"]
    assert sorted((r.outcome, r.code) for r in twin) == [
        ("accepted", None),
        ("rejected", "REPLAY_DETECTED"),
    ]
    assert verify(tmp_path / "audit.db").ok
    store.close()


def test_a_paired_row_is_not_put_once_the_trail_is_gone(tmp_path: Path, clock: ManualClock) -> None:
    """The trail's live segment deleted under a running gateway: the paired batch puts no
    accepted row into the outbox (it would drain into nothing); the command is refused
    ``STATE_UNAVAILABLE`` as before, its msg_id spent; with the trail back, commands pass."""
    store = sqlite_store(tmp_path / "state.db", clock=clock)
    trail = tmp_path / "audit.db"
    audit = AuditLog(trail, clock=clock)
    audit.attach(store.outbox())
    receiver = fresh_receiver(SecurityConfig(), registry(), store, audit, clock)

    async def offload(fn: Callable[..., Any], *args: Any) -> Any:
        return fn(*args)

    def outbox_rows() -> list[tuple[str, str]]:
        query = "SELECT json_extract(row, '$.msg_id'), json_extract(row, '$.outcome') FROM outbox"
        return store.read_outbox(lambda db: db.execute(query).fetchall())

    aside = trail.rename(tmp_path / "aside.db")
    gone = asyncio.run(receiver.receive_async(signed(msg_id="gone-1"), None, offload))
    assert (gone.accepted, gone.code) == (False, "STATE_UNAVAILABLE")
    assert ("gone-1", "accepted") not in outbox_rows()
    aside.rename(trail)
    back = asyncio.run(receiver.receive_async(signed(msg_id="back-1"), None, offload))
    assert back.accepted
    receiver.close()
    rows = [(r.msg_id, r.outcome) for r in AuditLog(trail).tail(20)]
    assert ("gone-1", "accepted") not in rows and ("back-1", "accepted") in rows
    store.close()


def test_a_trail_that_cannot_be_stated_is_unavailable_typed(
    tmp_path: Path, clock: ManualClock
) -> None:
    """The trail's directory replaced by a regular file (``stat``: ENOTDIR, as EIO or
    EACCES): never a raw ``OSError`` from the loop or the state writer's batch.  Commands
    are refused ``STATE_UNAVAILABLE``; a fresh ESTOP, alone or between paired commands, is
    delivered flagged ``AUDIT_UNAVAILABLE``, its row spilled and its entry recorded."""
    store = sqlite_store(tmp_path / "state.db", clock=clock)
    (tmp_path / "trail").mkdir()
    audit = AuditLog(tmp_path / "trail" / "audit.db", clock=clock, spill_path=tmp_path / "s.db")
    audit.attach(store.outbox())
    receiver = fresh_receiver(SecurityConfig(), registry(), store, audit, clock)

    async def offload(fn: Callable[..., Any], *args: Any) -> Any:
        return fn(*args)

    def estop(msg_id: str) -> bytes:
        return signed(type=6, safety_event="ESTOP", cmd="estop", msg_id=msg_id)

    async def scenario() -> list[Outcome]:
        first = await receiver.receive_async(signed(msg_id="cmd-1"), None, offload)
        alone = await receiver.receive_async(estop("es-1"), None, offload, offload)
        mixed = await asyncio.gather(
            receiver.receive_async(signed(msg_id="cmd-2"), None, offload),
            receiver.receive_async(estop("es-2"), None, offload, offload),
            receiver.receive_async(signed(msg_id="cmd-3"), None, offload),
        )
        return [first, alone, *mixed]

    assert asyncio.run(receiver.receive_async(signed(msg_id="ok-1"), None, offload)).accepted
    (tmp_path / "trail").rename(tmp_path / "aside")
    (tmp_path / "trail").write_text("not a directory")
    cmd1, es1, cmd2, es2, cmd3 = asyncio.run(scenario())
    for refused in (cmd1, cmd2, cmd3):
        assert (refused.accepted, refused.code) == (False, "STATE_UNAVAILABLE")
    for delivered in (es1, es2):
        assert delivered.accepted and delivered.warning == "AUDIT_UNAVAILABLE"
    assert receiver.stats.spilled == 2
    keys = store.read_outbox(lambda db: {k for (k,) in db.execute("SELECT key FROM seen")})
    assert {"es-1", "es-2"} <= keys
    receiver.close()
    store.close()
