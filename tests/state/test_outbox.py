"""The audit outbox: one fsync per batch for an accepted message's entry and row, refusals
answered before their fsync, kill -9 at the worst points, processes sharing one state."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import sqlite3
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from antireplay import SecurityConfig
from antireplay.audit import AuditLog, verify
from antireplay.core.clock import ManualClock
from antireplay.core.errors import StateUnavailableError
from antireplay.core.window import Seen
from antireplay.state.sqlite import SqliteStore
from harness import fresh_receiver
from harness.envelopes import NOW, registry, signed
from harness.stores import sqlite_store

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": f"{ROOT / 'src'}{os.pathsep}{ROOT}"}
WORKER = [sys.executable, "-m", "harness.workers.outbox_worker"]
#: Fsyncs of opening and closing a store and a trail (creating files, keys, the head).
SETUP_FSYNCS = 40
#: One row of ``strace -c``'s table: % time, seconds, usecs/call, calls, [errors], the call.
SYNC_ROW = re.compile(r"^\s*[\d.]+\s+[\d.]+\s+\d+\s+(\d+)\s+(?:\d+\s+)?f(?:data)?sync$", re.M)


def traced(where: Path, *args: str) -> tuple[int, int, int]:
    """Run the worker under ``strace -f -c``: (fsync + fdatasync calls, batches, ops)."""
    log = where / "strace.txt"
    out = subprocess.run(
        ["strace", "-f", "-c", "-e", "trace=fsync,fdatasync", "-o", str(log), *WORKER,
         str(where), *args],
        capture_output=True, text=True, cwd=ROOT, env=ENV, check=True, timeout=120,
    ).stdout  # fmt: skip
    calls = sum(int(m[1]) for m in SYNC_ROW.finditer(log.read_text()))
    found = re.search(r"BATCHES (\d+) OPS (\d+)", out)
    assert found is not None, out
    return calls, int(found[1]), int(found[2])


def test_an_accepted_message_costs_one_fsync_not_three(tmp_path: Path) -> None:
    """Sequential (c=1): the entry commits without an fsync, its row's batch fsyncs once
    and covers both; the witness and the trail sync by time, not per batch."""
    n = 200
    fsyncs, _, _ = traced(tmp_path, "accept", str(n), "1")
    assert n <= fsyncs <= n + SETUP_FSYNCS, f"{fsyncs} fsyncs for {n} accepted messages"


def test_concurrent_accepts_cost_at_most_one_fsync_per_batch(tmp_path: Path) -> None:
    n = 640
    fsyncs, batches, ops = traced(tmp_path, "accept", str(n), "32")
    assert ops == 2 * n  # each message: its entry and its row, through one committer
    assert fsyncs <= batches + SETUP_FSYNCS, f"{fsyncs} fsyncs for {batches} batches"
    assert fsyncs < n, f"{fsyncs} fsyncs for {n} accepted messages"


@pytest.mark.parametrize("driver", ["paired", "paired-threads"])
def test_a_paired_accept_is_one_operation_and_batches_fsync_once(
    tmp_path: Path, driver: str
) -> None:
    """Either driver's trip (event loop, threads): entry and row ONE operation (not two),
    one fsync per batch."""
    n = 640
    fsyncs, batches, ops = traced(tmp_path, driver, str(n), "32")
    assert ops == n
    assert fsyncs <= batches + SETUP_FSYNCS, f"{fsyncs} fsyncs for {batches} batches"
    assert fsyncs < n, f"{fsyncs} fsyncs for {n} accepted messages"


def test_a_paired_accept_is_fsynced_before_its_answer(tmp_path: Path) -> None:
    """Persist, then believe: one at a time (c=1), each paired entry and row is answered
    only after an fsync of its own batch (``Paired.durable``), like an ``accept``'s row."""
    n = 60
    fsyncs, _, _ = traced(tmp_path, "paired", str(n), "1")
    assert n <= fsyncs <= n + SETUP_FSYNCS, f"{fsyncs} fsyncs for {n} accepted messages"


def test_refusals_are_answered_without_an_fsync(tmp_path: Path) -> None:
    fsyncs, batches, _ = traced(tmp_path, "refuse", "200")
    assert batches >= 200 and fsyncs <= SETUP_FSYNCS


def accepted_rows(trail: Path) -> Counter[str]:
    db = sqlite3.connect(f"file:{trail}?mode=ro", uri=True)
    try:
        found = db.execute("SELECT msg_id FROM audit WHERE outcome = 'accepted'").fetchall()
    finally:
        db.close()
    return Counter(m for (m,) in found)


def outbox_rows(state: Path) -> int:
    db = sqlite3.connect(f"file:{state}?mode=ro", uri=True)
    try:
        return int(db.execute("SELECT count(*) FROM outbox").fetchone()[0])
    finally:
        db.close()


def reopen(where: Path) -> tuple[SqliteStore, AuditLog]:
    """A restart: the store, then the trail, which drains the outbox first."""
    store = SqliteStore(where / "state.db")
    audit = AuditLog(where / "audit.db", clock=ManualClock())
    audit.attach(store.outbox())
    return store, audit


def run_until(where: Path, line: str, *args: str) -> list[str]:
    """Start the worker, SIGKILL it once it prints ``line``; what it printed before."""
    worker = subprocess.Popen(
        [*WORKER, str(where), *args], stdout=subprocess.PIPE, text=True, cwd=ROOT, env=ENV
    )
    printed: list[str] = []
    try:
        assert worker.stdout is not None
        for got in worker.stdout:
            if got.strip() == line:
                break
            printed.append(got.strip())
        else:
            pytest.fail(f"the worker exited ({worker.wait()}) before {line}")
    finally:
        worker.send_signal(signal.SIGKILL)
        worker.wait()
    return printed


def test_kill_9_between_the_trail_commit_and_the_outbox_delete_duplicates_nothing(
    tmp_path: Path,
) -> None:
    n = 50
    run_until(tmp_path, "STOP", "hang-forget", str(n))
    assert outbox_rows(tmp_path / "state.db") == n  # moved, durable, not yet deleted
    assert accepted_rows(tmp_path / "audit.db") == Counter({f"h{i}": 1 for i in range(n)})
    store, audit = reopen(tmp_path)
    audit.close()
    store.close()
    assert accepted_rows(tmp_path / "audit.db") == Counter({f"h{i}": 1 for i in range(n)})
    assert outbox_rows(tmp_path / "state.db") == 0
    report = verify(tmp_path / "audit.db")
    assert report.chain_ok and report.head == "match", report.lines()


def seen_keys(state: Path) -> set[str]:
    db = sqlite3.connect(f"file:{state}?mode=ro", uri=True)
    try:
        return {k for (k,) in db.execute("SELECT key FROM seen")}
    finally:
        db.close()


def outbox_accepted(state: Path) -> Counter[str]:
    db = sqlite3.connect(f"file:{state}?mode=ro", uri=True)
    try:
        found = db.execute("SELECT json_extract(row, '$.msg_id') FROM outbox").fetchall()
    finally:
        db.close()
    return Counter(m for (m,) in found)


@pytest.mark.parametrize("driver", ["paired", "paired-threads"])
@pytest.mark.parametrize("hang", [0, 7, 150])
def test_kill_9_inside_a_paired_batch_keeps_entry_and_row_together(
    tmp_path: Path, hang: int, driver: str
) -> None:
    """Killed inside a batch's transaction (a row being built, its entry written but not
    committed), under either driver (event loop, threads): that batch leaves neither
    entries nor rows; every answered message has both; no entry without its row, no row
    without its entry, before and after a restart."""
    printed = run_until(tmp_path, "HANG", driver, "200", "16", str(hang))
    answered = {line.split()[1] for line in printed if line.startswith("ANSWERED")}
    assert f"p{hang}" not in answered
    seen = seen_keys(tmp_path / "state.db")
    trail, waiting = accepted_rows(tmp_path / "audit.db"), outbox_accepted(tmp_path / "state.db")
    assert answered <= seen
    assert f"p{hang}" not in seen
    assert set(trail) | set(waiting) == seen  # moved rows stay in the outbox until durable
    assert max([*trail.values(), *waiting.values(), 1]) == 1
    store, audit = reopen(tmp_path)
    audit.close()
    store.close()
    assert accepted_rows(tmp_path / "audit.db") == Counter(dict.fromkeys(seen, 1))
    assert outbox_rows(tmp_path / "state.db") == 0
    report = verify(tmp_path / "audit.db")
    assert report.chain_ok and report.head == "match", report.lines()


def test_a_refusal_answered_before_its_fsync_survives_kill_9(tmp_path: Path) -> None:
    run_until(tmp_path, "ANSWERED", "hang-refused")
    store, audit = reopen(tmp_path)
    try:
        refused = [r for r in audit.tail(10) if r.msg_id == "refused-1"]
    finally:
        audit.close()
        store.close()
    assert len(refused) == 1 and refused[0].code == "REPLAY_DETECTED"
    assert verify(tmp_path / "audit.db").chain_ok


def test_processes_sharing_one_state_and_trail_accept_once_and_chain_once(
    tmp_path: Path,
) -> None:
    keys = [f"race-{i}" for i in range(150)]
    SqliteStore(tmp_path / "state.db").close()  # made once, before the racers open it
    command = [*WORKER, str(tmp_path), "race", ",".join(keys)]
    racers = [
        subprocess.Popen(command, stdout=subprocess.PIPE, text=True, cwd=ROOT, env=ENV)
        for _ in range(3)
    ]
    won: Counter[str] = Counter()
    for racer in racers:
        out, _ = racer.communicate(timeout=120)
        assert racer.returncode == 0
        won.update(line.split()[1] for line in out.splitlines() if line.startswith("WON"))
    assert won == Counter(dict.fromkeys(keys, 1))  # exactly one acceptance per key
    assert accepted_rows(tmp_path / "audit.db") == won  # each audited once, none lost
    assert outbox_rows(tmp_path / "state.db") == 0
    report = verify(tmp_path / "audit.db")
    assert report.chain_ok and report.head == "match", report.lines()


def test_a_live_rollback_noticed_by_an_outbox_only_batch_is_still_audited(
    tmp_path: Path,
) -> None:
    """The state restored under a running gateway, noticed first by a batch of one outbox
    Forget (no seen-set record to tell): the loss waits for the next record, which puts a
    ``STATE_LOST`` row on the trail (open + live: two), never consumed silently."""
    clock = ManualClock(wall=NOW)
    store = sqlite_store(tmp_path / "state.db", clock=clock)
    audit = AuditLog(tmp_path / "audit.db", clock=clock)
    audit.attach(store.outbox())
    receiver = fresh_receiver(SecurityConfig(), registry(), store, audit, clock)
    assert receiver.receive(signed(msg_id="a")).accepted
    db = sqlite3.connect(tmp_path / "state.db")
    db.execute("UPDATE meta SET generation = 0")
    db.commit()
    db.close()
    store.outbox().flush()  # a batch of one Forget notices the rollback
    clock.step_wall(60)
    assert receiver.receive(signed(msg_id="c", timestamp=NOW + 60)).accepted
    receiver.close()
    assert receiver.stats.losses == 2
    rows = [r.outcome for r in AuditLog(tmp_path / "audit.db").tail(20)]
    assert rows.count("state") == 2
    store.close()


def test_a_row_that_raises_fails_its_own_operation_only(tmp_path: Path) -> None:
    """A paired row builder that raises: its operation is answered a typed
    ``StateUnavailableError``; an ESTOP's record and a paired command sharing the writer
    commit as usual."""
    store = SqliteStore(tmp_path / "state.db")
    audit = AuditLog(tmp_path / "audit.db", clock=ManualClock(wall=NOW))
    audit.attach(store.outbox())

    def broken(seen: Seen) -> str | None:
        raise ValueError("no row")

    async def scenario() -> list[object]:
        return list(
            await asyncio.gather(
                store.commit_with_row_async("bad", NOW + 30, NOW, broken),
                store.commit_async("estop", NOW + 30, NOW, True),
                store.commit_with_row_async("good", NOW + 30, NOW, lambda seen: None),
                return_exceptions=True,
            )
        )

    bad, estop, good = asyncio.run(scenario())
    assert isinstance(bad, tuple) and isinstance(bad[0], StateUnavailableError)
    assert isinstance(estop, Seen) and estop.recorded
    assert isinstance(good, tuple) and isinstance(good[0], Seen) and good[0].recorded
    audit.close()
    store.close()
