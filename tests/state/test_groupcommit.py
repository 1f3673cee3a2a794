"""Group commit: batching, per-caller results, failure isolation, and kill -9 mid-batch.

The unit tests hold the writer inside ``run_batch`` with an Event so that a batch
forms for certain (no sleeps decide anything).  The end-to-end test runs the real
``antireplay serve`` on its default durable config, SIGKILLs it under concurrent
load at seeded moments, restarts it on the same state and replays every message
that was sent: nothing is accepted twice, every answered request is audited and
recorded, and the audit chain verifies.
"""

from __future__ import annotations

import asyncio
import json
import os
import queue
import random
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

from antireplay.audit import AuditLog, AuditRow, verify
from antireplay.cli.demo import JSON, command, load_operator_key, write_demo_config
from antireplay.state import groupcommit
from antireplay.state.groupcommit import GroupCommitter
from antireplay.state.sqlite import SqliteStore
from harness import GatewayProcess

WAIT_S = 30.0  # liveness bound only: a correct run never gets near it


def _until(condition: Callable[[], bool], what: str) -> None:
    """Wait for a condition the test itself brings about (a bound, never a timing guess)."""
    deadline = time.monotonic() + WAIT_S
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.001)


class HeldWriter:
    """A ``run_batch`` that records every batch and holds the writer inside the first one
    until released, so that everything submitted meanwhile queues into one batch."""

    def __init__(self, fail_if: Callable[[Sequence[int]], bool] = lambda _: False) -> None:
        self.batches: list[list[int]] = []
        self.entered = threading.Event()
        self.release = threading.Event()
        self.fail_if = fail_if

    def __call__(self, ops: Sequence[int]) -> list[tuple[int, int]]:
        self.batches.append(list(ops))
        if len(self.batches) == 1:
            self.entered.set()
            if not self.release.wait(WAIT_S):
                raise TimeoutError("test never released the writer")
        if self.fail_if(ops):
            raise ValueError(f"batch of {len(ops)} failed")
        return [(op, i) for i, op in enumerate(ops)]  # result names its op and its position


def _race(
    committer: GroupCommitter[int, tuple[int, int]], ops: Sequence[int]
) -> tuple[list[threading.Thread], dict[int, object]]:
    """One thread per op, released together by a barrier; returns threads and outcomes."""
    barrier = threading.Barrier(len(ops))
    outcomes: dict[int, object] = {}

    def submit(op: int) -> None:
        barrier.wait()
        try:
            outcomes[op] = committer.submit(op)
        except Exception as exc:  # the outcome under test
            outcomes[op] = exc

    threads = [threading.Thread(target=submit, args=(op,)) for op in ops]
    for thread in threads:
        thread.start()
    return threads, outcomes


def _hold_first_batch(
    writer: HeldWriter, committer: GroupCommitter[int, tuple[int, int]]
) -> threading.Thread:
    """Submit op -1 and wait until the writer is inside its batch."""
    first = threading.Thread(target=committer.submit, args=(-1,))
    first.start()
    if not writer.entered.wait(WAIT_S):
        pytest.fail("writer never entered run_batch")
    return first


def _join(threads: Sequence[threading.Thread]) -> None:
    for thread in threads:
        thread.join(WAIT_S)
        if thread.is_alive():
            pytest.fail("a caller was never answered")


def test_racing_submits_share_a_batch_and_each_gets_its_own_result() -> None:
    writer = HeldWriter()
    committer: GroupCommitter[int, tuple[int, int]] = GroupCommitter(writer, name="t-batch")
    try:
        first = _hold_first_batch(writer, committer)
        ops = list(range(32))
        threads, outcomes = _race(committer, ops)
        _until(lambda: committer._queue.qsize() == len(ops), "every racer queued")
        writer.release.set()
        _join([first, *threads])
    finally:
        committer.close()
    assert writer.batches[0] == [-1]
    assert len(writer.batches) == 2 and sorted(writer.batches[1]) == ops
    for op in ops:  # each caller got the result at its own op's position, not a neighbour's
        assert outcomes[op] == (op, writer.batches[1].index(op))
    assert (committer.batches, committer.operations) == (2, len(ops) + 1)


def test_a_failed_batch_raises_in_every_caller_and_the_next_batch_works() -> None:
    writer = HeldWriter(fail_if=lambda ops: 13 in ops)
    committer: GroupCommitter[int, tuple[int, int]] = GroupCommitter(writer, name="t-fail")
    try:
        first = _hold_first_batch(writer, committer)
        ops = list(range(20))  # 13 poisons the whole batch
        threads, outcomes = _race(committer, ops)
        _until(lambda: committer._queue.qsize() == len(ops), "every racer queued")
        writer.release.set()
        _join([first, *threads])
        errors = {id(outcomes[op]) for op in ops}
        assert len(errors) == 1  # one error, raised in every caller of the batch
        assert isinstance(outcomes[0], ValueError) and "batch of 20 failed" in str(outcomes[0])
        assert committer.submit(99) == (99, 0)  # the writer survived: the next batch works
    finally:
        committer.close()
    assert writer.batches == [[-1], writer.batches[1], [99]]
    assert (committer.batches, committer.operations) == (2, 2)  # the failed one not counted


def test_a_withdrawn_operation_is_never_run_and_a_taken_one_cannot_be_withdrawn() -> None:
    """A caller that stops waiting cancels its future: withdrawn while queued, the writer
    skips it; once taken into a batch it can no longer be withdrawn and is committed."""
    writer = HeldWriter()
    committer: GroupCommitter[int, tuple[int, int]] = GroupCommitter(writer, name="t-cancel")
    try:
        taken = committer.enqueue(1)
        _until(writer.entered.is_set, "the writer to take the first batch")
        queued, kept = committer.enqueue(2), committer.enqueue(3)
        assert not taken.cancel()  # in the running batch
        assert queued.cancel()
        writer.release.set()
        assert taken.result(WAIT_S) == (1, 0)
        assert kept.result(WAIT_S) == (3, 0)  # alone in its batch: 2 was skipped
        assert writer.batches == [[1], [3]]
    finally:
        writer.release.set()
        committer.close()


def test_event_loop_waiters_get_their_results_in_one_call_per_batch() -> None:
    """enqueue_async: no thread held while waiting, and the writer wakes the loop once per
    batch, not once per waiter; a failed batch fails every waiter of it."""
    writer = HeldWriter()
    committer: GroupCommitter[int, tuple[int, int]] = GroupCommitter(writer, name="t-loop")
    wakeups: list[int] = []

    async def scenario() -> tuple[list[Any], list[Any]]:
        loop = asyncio.get_running_loop()
        real = loop.call_soon_threadsafe

        def counting(callback: Any, *args: Any) -> Any:
            if callback is groupcommit._deliver:
                wakeups.append(len(args[0]))
            return real(callback, *args)

        loop.call_soon_threadsafe = counting  # type: ignore[method-assign,assignment]
        first = _hold_first_batch(writer, committer)
        waiters = [committer.enqueue_async(op) for op in range(16)]
        writer.release.set()
        results = await asyncio.gather(*waiters, return_exceptions=True)
        writer.fail_if = lambda ops: True
        failed = await asyncio.gather(
            *(committer.enqueue_async(op) for op in (100, 101)), return_exceptions=True
        )
        await asyncio.to_thread(_join, [first])
        return results, failed

    try:
        results, failed = asyncio.run(scenario())
    finally:
        committer.close()
    assert writer.batches[:2] == [[-1], list(range(16))]
    assert results == [(op, op) for op in range(16)]
    assert wakeups[0] == 16  # sixteen waiters, one call into the loop
    assert all(isinstance(f, ValueError) for f in failed)


def test_close_finishes_what_is_queued_then_refuses() -> None:
    writer = HeldWriter()
    committer: GroupCommitter[int, tuple[int, int]] = GroupCommitter(writer, name="t-close")
    first = _hold_first_batch(writer, committer)
    ops = list(range(10))
    threads, outcomes = _race(committer, ops)
    _until(lambda: committer._queue.qsize() == len(ops), "every racer queued")
    closer = threading.Thread(target=committer.close)
    closer.start()
    _until(lambda: committer._queue.qsize() == len(ops) + 1, "close() queued its stop")
    writer.release.set()
    _join([closer, first, *threads])
    assert sorted(writer.batches[1]) == ops
    assert all(outcomes[op] == (op, writer.batches[1].index(op)) for op in ops)
    with pytest.raises(RuntimeError, match="closed"):
        committer.submit(1)


class _PausingQueue:
    """The committer's queue, pausing a submitter between its ``closed`` check and its put."""

    def __init__(self, inner: queue.SimpleQueue[Any]) -> None:
        self.inner = inner
        self.checked = threading.Event()
        self.go = threading.Event()
        self.put_done = threading.Event()

    def put(self, item: Any) -> None:
        if item is not None and not self.checked.is_set():
            self.checked.set()
            self.go.wait(WAIT_S)
            self.inner.put(item)
            self.put_done.set()
            return
        self.inner.put(item)

    def get(self) -> Any:
        return self.inner.get()

    def get_nowait(self) -> Any:
        return self.inner.get_nowait()


def test_submit_racing_close_is_answered_or_refused_never_left_waiting() -> None:
    """A caller paused between its ``closed`` check and its put while close() runs: the close
    waits for the put (one gate), so the operation is committed, never left waiting."""
    committer: GroupCommitter[int, int] = GroupCommitter(list, name="t-race")
    pausing = _PausingQueue(committer._queue)
    committer._queue = pausing  # type: ignore[assignment]
    outcome: list[object] = []

    def late_caller() -> None:
        try:
            outcome.append(committer.submit(7))
        except RuntimeError as exc:
            outcome.append(exc)

    caller = threading.Thread(target=late_caller, daemon=True)
    caller.start()
    if not pausing.checked.wait(WAIT_S):
        pytest.fail("caller never reached its put")
    closer = threading.Thread(target=committer.close, daemon=True)
    closer.start()  # races the paused caller
    pausing.go.set()
    if not pausing.put_done.wait(WAIT_S):
        pytest.fail("caller never queued its operation")
    caller.join(WAIT_S)  # bounds a hang; when correct the answer comes at once
    closer.join(WAIT_S)
    assert not caller.is_alive(), "submit() racing close() never returned"
    assert not closer.is_alive()
    assert outcome == [7]


# --- SqliteStore under concurrency ---------------------------------------------------------------


def test_sqlite_store_racers_get_one_winner_per_key_in_few_fsyncs(tmp_path: Path) -> None:
    store = SqliteStore(tmp_path / "state.db")
    witness_writes = 0
    write = store.witness.write

    def counting_write(deployment: str, generation: int, wall: float, *, sync: bool) -> None:
        nonlocal witness_writes
        witness_writes += 1  # one write per durable transaction (its fdatasync deferred)
        write(deployment, generation, wall, sync=sync)

    store.witness.write = counting_write  # type: ignore[method-assign,assignment]
    keys = [f"key-{i}" for i in range(200)]
    n_threads = 16
    barrier = threading.Barrier(n_threads)
    recorded: Counter[str] = Counter()
    lock = threading.Lock()
    now = time.time()

    def racer(seed: int) -> None:
        order = keys[:]
        random.Random(seed).shuffle(order)
        barrier.wait()
        for key in order:
            if store.commit(key, now + 30.0, now).recorded:
                with lock:
                    recorded[key] += 1

    threads = [threading.Thread(target=racer, args=(i,)) for i in range(n_threads)]
    try:
        for thread in threads:
            thread.start()
        _join(threads)
        committer = store._committer
        batches, operations = committer.batches, committer.operations
        assert store.count() == len(keys)
    finally:
        store.close()
    assert recorded == dict.fromkeys(keys, 1)  # exactly one winner per key
    assert operations == n_threads * len(keys)
    assert witness_writes == batches  # one durable write per batch, not per commit
    assert batches * 4 <= operations, f"{batches} batches for {operations} commits"


def test_audit_racers_get_distinct_seqs_one_chain_and_few_checkpoints(tmp_path: Path) -> None:
    audit = AuditLog(tmp_path / "audit.db")
    n_threads, per_thread = 16, 50
    barrier = threading.Barrier(n_threads)
    seqs: list[int] = []
    lock = threading.Lock()

    def racer(thread: int) -> None:
        barrier.wait()
        for i in range(per_thread):
            seq = audit.append(AuditRow(
                at=time.time(), outcome="rejected", code="REPLAY_DETECTED", warning=None,
                msg_type=1, sender="operator", sender_verified=True, msg_id=f"m-{thread}-{i}",
            ))  # fmt: skip
            with lock:
                seqs.append(seq)

    threads = [threading.Thread(target=racer, args=(i,)) for i in range(n_threads)]
    try:
        for thread in threads:
            thread.start()
        _join(threads)
        batches, operations = audit._committer.batches, audit._committer.operations
    finally:
        audit.close()
    assert sorted(seqs) == list(range(1, n_threads * per_thread + 1))  # each caller its own row
    report = verify(tmp_path / "audit.db")
    assert report.ok and report.after_checkpoint == 0, report.lines()
    assert operations == n_threads * per_thread
    assert batches * 4 <= operations, f"{batches} batches (fsyncs) for {operations} rows"


# --- kill -9 under concurrent load, restart, replay everything ----------------------------------

CLIENTS = 16
ROUNDS = (11, 23, 37)  # seeds: where each kill lands
ACCEPTED_ROWS = "SELECT msg_id FROM audit WHERE outcome = 'accepted'"
#: Accepted rows the state database's outbox holds, not yet moved into the trail.
OUTBOX_ACCEPTED = (
    "SELECT json_extract(row, '$.msg_id') FROM outbox"
    " WHERE json_extract(row, '$.outcome') = 'accepted'"
)


@dataclass
class Sent:
    """One distinct message and every answer it got (HTTP status or ``"error"``)."""

    raw: bytes
    msg_id: str
    before_kill: list[int | str] = field(default_factory=list)
    after_restart: list[tuple[int, str | None]] = field(default_factory=list)


def _answer(http: httpx.Client, raw: bytes) -> tuple[int | str, dict[str, Any]]:
    try:
        reply = http.post("/v1/messages", content=raw, headers=JSON)
    except httpx.TransportError:
        return "error", {}
    try:
        body = reply.json()
    except ValueError:
        body = {}
    return reply.status_code, body if isinstance(body, dict) else {}


class Load:
    """CLIENTS threads sending distinct signed commands (and some replays) until the
    gateway dies: the client that gets answer number ``kill_after`` SIGKILLs it at once,
    while the others' requests are inside it (parsed, verified, queued or committing)."""

    def __init__(self, gw: GatewayProcess, state: Path, seed: int) -> None:
        self.gw = gw
        self.key = load_operator_key(state)
        self.rng = random.Random(seed)
        self.kill_after = self.rng.randrange(40, 200)
        self.sent: dict[str, Sent] = {}
        self.answered = 0
        self.lock = threading.Lock()
        assert gw.proc is not None
        self.pid = gw.proc.pid

    def client(self, seed: int, barrier: threading.Barrier) -> None:
        rng = random.Random(seed)
        mine: list[Sent] = []
        with httpx.Client(base_url=self.gw.url, timeout=WAIT_S) as http:
            barrier.wait()
            while True:
                if mine and rng.random() < 0.2:  # a replay of something already sent
                    msg = rng.choice(mine)
                else:
                    raw = command(self.key)
                    msg = Sent(raw, json.loads(raw)["msg_id"])
                    mine.append(msg)
                    with self.lock:
                        self.sent[msg.msg_id] = msg
                status, _ = _answer(http, msg.raw)
                with self.lock:
                    msg.before_kill.append(status)
                    if status == "error":
                        return
                    self.answered += 1
                    if self.answered == self.kill_after:  # at once, from the answered thread
                        os.kill(self.pid, signal.SIGKILL)

    def run_and_kill(self) -> None:
        barrier = threading.Barrier(CLIENTS)
        seeds = [self.rng.randrange(2**32) for _ in range(CLIENTS)]
        threads = [threading.Thread(target=self.client, args=(s, barrier)) for s in seeds]
        for thread in threads:
            thread.start()
        assert self.gw.proc is not None
        try:
            self.gw.proc.wait(WAIT_S)  # SIGKILLed by a client, CLIENTS requests in flight
        except subprocess.TimeoutExpired:
            self.gw.proc.kill()
            pytest.fail(f"only {self.answered} answers, no kill")
        self.gw.proc = None
        _join(threads)


def _replay_all(gw: GatewayProcess, sent: Sequence[Sent]) -> None:
    """Replay every message, concurrently (so the restarted gateway group-commits too)."""
    work: queue.SimpleQueue[Sent] = queue.SimpleQueue()
    for msg in sent:
        work.put(msg)

    def worker() -> None:
        with httpx.Client(base_url=gw.url, timeout=WAIT_S) as http:
            while True:
                try:
                    msg = work.get_nowait()
                except queue.Empty:
                    return
                status, body = _answer(http, msg.raw)
                code = body.get("detail") or body.get("code")
                msg.after_restart.append((status, code) if isinstance(status, int) else (0, status))

    threads = [threading.Thread(target=worker) for _ in range(CLIENTS)]
    for thread in threads:
        thread.start()
    _join(threads)


def _rows(db: Path, sql: str) -> list[tuple[Any, ...]]:
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return conn.execute(sql).fetchall()
    finally:
        conn.close()


def _refused(answer: tuple[int, str | None]) -> bool:
    """409 (already spent) or 408 restart_fence (a kill mid-batch may leave a fence)."""
    return answer[0] == 409 or answer == (408, "restart_fence")


@pytest.mark.parametrize("seed", ROUNDS)
def test_kill_9_mid_group_commit_then_replay_everything(tmp_path: Path, seed: int) -> None:
    gw = GatewayProcess(write_demo_config(tmp_path))
    gw.start()
    try:
        load = Load(gw, tmp_path, seed)
        load.run_and_kill()
        sent = list(load.sent.values())
        answered_200 = {m.msg_id for m in sent if 200 in m.before_kill}
        assert answered_200 and all(m.before_kill.count(200) <= 1 for m in sent)
        assert sum("error" in m.before_kill for m in sent) >= 1  # requests cut off by the kill

        # Right after the kill: the chain is intact and the checkpoint matches a row of it
        # (rows committed after the last checkpoint are reported, not a break).
        report = verify(tmp_path / "audit.db")
        assert report.chain_ok and report.head == "match", report.lines()
        # No answered message unrecorded, none unaudited: its row is in the trail, or in
        # the state database's outbox, moved into the trail by the next start.
        seen = {k for (k,) in _rows(tmp_path / "state.db", "SELECT key FROM seen")}
        assert answered_200 <= seen
        audited = _rows(tmp_path / "audit.db", ACCEPTED_ROWS)
        assert report.records >= len(audited)
        waiting = _rows(tmp_path / "state.db", OUTBOX_ACCEPTED)
        assert answered_200 <= {m for (m,) in audited + waiting}

        gw.start()  # the same state, the same port
        _replay_all(gw, sent)
        for msg in sent:
            (again,) = msg.after_restart
            if msg.msg_id in answered_200 or msg.msg_id in seen:  # committed before the kill
                assert _refused(again), (msg.msg_id, again)
            else:  # never committed: may be accepted now, once (or fenced)
                assert again[0] == 200 or _refused(again), (msg.msg_id, again)
        late = [m for m in sent if m.after_restart[0][0] == 200]
        _replay_all(gw, late)  # accepted once after the restart: spent now too
        assert all(_refused(m.after_restart[1]) for m in late)
    finally:
        gw.stop()

    accepted = [m.msg_id for m in sent if 200 in m.before_kill + [a[0] for a in m.after_restart]]
    for msg in sent:  # nothing accepted twice, over both lives of the gateway
        assert (msg.before_kill + [a[0] for a in msg.after_restart]).count(200) <= 1
    audit_accepts = Counter(m for (m,) in _rows(tmp_path / "audit.db", ACCEPTED_ROWS))
    assert all(audit_accepts[m] == 1 for m in accepted)
    # The outbox drained into one intact chain, nothing left behind.
    assert _rows(tmp_path / "state.db", "SELECT count(*) FROM outbox") == [(0,)]
    report = verify(tmp_path / "audit.db")
    assert report.chain_ok and report.head == "match", report.lines()
    assert max(audit_accepts.values()) == 1
    cli = subprocess.run(
        [sys.executable, "-m", "antireplay", "audit", "verify", str(tmp_path / "audit.db")],
        capture_output=True,
        text=True,
        check=False,
        timeout=WAIT_S,
    )
    assert cli.returncode == 0, cli.stdout + cli.stderr
    assert "chain intact" in cli.stdout and "MAC verified" in cli.stdout
