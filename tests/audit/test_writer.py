"""The audit writer when its trail is deleted (refused at start, refused while running),
and a real writer killed with SIGKILL at each step of a rotation."""

from __future__ import annotations

import hmac
import logging
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
from prometheus_client import CollectorRegistry

from antireplay import ManualClock, SecurityConfig
from antireplay.audit import AuditLog, AuditRow, Retention, tail, verify
from antireplay.audit.segments import bytes_of, rotated
from antireplay.core.errors import AuditFileError, StateUnavailableError
from antireplay.http.metrics import StateCollector
from antireplay.http.status import rolled_back
from harness import ROOT, fresh_receiver
from harness.audit import SMALL_SEGMENT, append, trail
from harness.envelopes import registry, signed
from harness.stores import sqlite_store
from harness.workers.audit_worker import BUDGET


@pytest.mark.parametrize("key_too", [False, True], ids=["db", "db-and-key"])
def test_a_refused_start_on_a_deleted_trail_creates_nothing(tmp_path: Path, key_too: bool) -> None:
    """``rm audit.db*`` under a running gateway (which rewrites its head afterwards): the next
    start refuses, says the trail was deleted and how many records the head says it held, and
    leaves no new empty trail behind for the start after that to adopt."""
    path = tmp_path / "audit.db"
    trail(path, 3)
    doomed = [path, *tmp_path.glob("audit.db-*")]
    if key_too:
        doomed.append(tmp_path / "audit.db.key")
    for file in doomed:
        file.unlink()
    with pytest.raises(AuditFileError) as err:
        AuditLog(path)
    assert "deleted" in err.value.problem
    assert "held 3 records" in err.value.problem
    assert not path.exists()


def test_a_running_writer_refuses_to_append_to_a_deleted_trail(tmp_path: Path) -> None:
    """Deleted under a running writer, a trail would swallow every later record with the
    unlinked file: the append fails (503 for the command) instead of being lost."""
    trail(tmp_path / "audit.db", 1)
    log = AuditLog(tmp_path / "audit.db")
    try:
        for file in tmp_path.glob("audit.db*"):
            file.unlink()
        with pytest.raises(StateUnavailableError, match="deleted or replaced"):
            log.append(AuditRow(
                at=1_800_000_100.0, outcome="accepted", code=None, warning=None, msg_type=1,
                sender="operator", sender_verified=True, msg_id="lost",
            ))  # fmt: skip
    finally:
        log.close()


def kill_at(path: Path, step: str, nth: int) -> list[int]:
    """Run a real writer appending in a loop, SIGKILL it once it hangs at ``step`` of its
    ``nth`` rotation (or retention); the sequence numbers it had acknowledged."""
    worker = subprocess.Popen(
        [sys.executable, "-m", "harness.workers.audit_worker", str(path), step, str(nth)],
        stdout=subprocess.PIPE, text=True, cwd=ROOT,
        env={**os.environ, "PYTHONPATH": f"{ROOT / 'src'}{os.pathsep}{ROOT}"},
    )  # fmt: skip
    acknowledged: list[int] = []
    try:
        assert worker.stdout is not None
        for line in worker.stdout:
            if line.startswith("STOP"):
                break
            acknowledged.append(int(line))
        else:
            pytest.fail(f"the writer exited ({worker.wait()}) before {step} #{nth}")
    finally:
        worker.send_signal(signal.SIGKILL)
        worker.wait()
    return acknowledged


@pytest.mark.parametrize("step", ["sealed", "prepared", "published", "retaining"])
def test_kill_9_mid_rotation_leaves_a_verifiable_trail_with_every_acknowledged_row(
    tmp_path: Path, step: str
) -> None:
    path = tmp_path / "audit.db"
    acknowledged = kill_at(path, step, 3)
    assert acknowledged == list(range(1, len(acknowledged) + 1))
    report = verify(path)
    assert report.chain_ok and report.head == "match", report.lines()
    assert report.after_checkpoint <= 1  # at most the row whose batch was rotating
    kept = {r.seq for r in tail(path, 10_000)}
    cut = report.first_row
    assert {seq for seq in acknowledged if seq >= cut} <= kept
    # a restart finishes or undoes the rotation and the trail goes on
    log = AuditLog(path, retention=Retention(segment_bytes=SMALL_SEGMENT))
    nxt = append(log, 10_000)
    log.close()
    assert report.last_row is not None and nxt == report.last_row + 1
    assert verify(path).ok and not path.with_name("audit.db.next").exists()
    assert all(file.name != f"{path.name}.next" for file in tmp_path.iterdir())


def rows_seen_by_another_process(path: Path) -> int:
    """Rows another process sees (its connection closes as it exits)."""
    count = "import sqlite3, sys; print(sqlite3.connect(sys.argv[1]).execute('SELECT count(*) FROM audit').fetchone()[0])"  # noqa: E501
    said = subprocess.run([sys.executable, "-c", count, str(path)], capture_output=True, check=True)
    return int(said.stdout)


def test_reading_the_trail_in_the_writers_process_keeps_its_wal(tmp_path: Path) -> None:
    """The status page reads the trail in the gateway's process: opening the file outside
    SQLite there would drop the writer's locks, and the next process to close its connection
    would delete the WAL the writer is appending to (its rows then lost)."""
    path = tmp_path / "audit.db"
    log = AuditLog(path)
    try:
        append(log, 0)
        assert [r.msg_id for r in tail(path, 5)] == ["m0"]  # read in the writer's process
        assert verify(path).ok
        assert rows_seen_by_another_process(path) == 1
        append(log, 1)
        assert rows_seen_by_another_process(path) == 2
    finally:
        log.close()
    assert verify(path).records == 2


def test_writer_processes_on_one_trail_rotate_and_retain_within_budget(tmp_path: Path) -> None:
    """Two real writer processes appending at once (``serve --workers 2``): the trail
    rotates and retention keeps it within ``max_bytes`` plus one segment whatever the
    interleaving, ``audit verify`` accepts the cut, and every acknowledged row kept is there
    exactly once."""
    path = tmp_path / "audit.db"
    AuditLog(path, retention=BUDGET).close()  # the key and head exist before both start
    env = {**os.environ, "PYTHONPATH": f"{ROOT / 'src'}{os.pathsep}{ROOT}"}
    command = [sys.executable, "-m", "harness.workers.audit_worker", str(path), "append"]
    workers = [
        subprocess.Popen(
            [*command, "700", name],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            env=env,
        )
        for name in ("a", "b")
    ]
    said: list[list[str]] = [[], []]

    def until(line: str) -> None:
        for worker, lines in zip(workers, said, strict=True):
            assert worker.stdin is not None and worker.stdout is not None
            while (got := worker.stdout.readline().strip()) != line:
                assert got, f"the writer exited ({worker.wait()}) before {line}"
                lines.append(got)
        for worker in workers:  # both are open together: now go on
            assert worker.stdin is not None
            worker.stdin.write("go\n")
            worker.stdin.flush()

    try:
        until("READY")
        until("DONE")  # both still open: the bound holds while they run
        on_disk = sum(bytes_of(file) for _, file in rotated(path)) + bytes_of(path)
        assert on_disk <= BUDGET.max_bytes + SMALL_SEGMENT  # type: ignore[operator]
    finally:
        for worker in workers:
            worker.communicate(timeout=60)
    assert [worker.returncode for worker in workers] == [0, 0]
    assert len(said[0]) == len(said[1]) == 700
    report = verify(path)
    assert report.ok and report.first_segment > 1, report.lines()  # rotated, and retained
    assert report.last_row == 1400  # every acknowledged row chained once: none lost, none twice
    kept = tail(path, 10_000)
    assert [r.seq for r in kept] == list(range(report.first_row, 1401))
    assert len({r.msg_id for r in kept}) == len(kept)
    assert {r.msg_id for r in kept} <= set(said[0]) | set(said[1])


class _TokenKey:
    """A head key in a token (``MacKey``) that can be pulled: then every MAC raises, as a
    failing PKCS#11 token does (``TokenUnavailableError`` is an ``OSError``)."""

    def __init__(self) -> None:
        self.down = False

    def mac(self, data: bytes, /) -> bytes:
        if self.down:
            raise OSError("token removed")
        return hmac.new(b"k" * 32, data, "sha256").digest()


def _head_behind(registry: CollectorRegistry) -> tuple[float | None, float | None]:
    return (
        registry.get_sample_value("antireplay_audit_head_behind"),
        registry.get_sample_value("antireplay_audit_head_failures_total"),
    )


def test_a_head_key_token_failing_on_a_sqlite_state_is_said_at_once_not_at_close(
    tmp_path: Path, clock: ManualClock, caplog: pytest.LogCaptureFixture
) -> None:
    """Commands keep being accepted (their rows reach the trail through the state's
    outbox) but the head checkpoint cannot be MACed: said at once, as a log line, the
    ``antireplay_audit_head_behind`` gauge, a failure counter and the readiness warning
    ``AUDIT_HEAD_BEHIND``; the outbox keeps the rows; with the token back the head
    catches up, the warning clears and the trail verifies with the key."""
    key = _TokenKey()
    store = sqlite_store(tmp_path / "state.db", clock=clock)
    audit = AuditLog(tmp_path / "audit.db", clock=clock, head_key=key)
    audit.attach(store.outbox())
    receiver = fresh_receiver(SecurityConfig(), registry(), store, audit, clock)
    metrics = CollectorRegistry()
    metrics.register(StateCollector(receiver))
    assert receiver.receive(signed(msg_id="before")).accepted
    assert _head_behind(metrics) == (0, 0) and rolled_back(audit) is None
    key.down = True
    clock.advance(audit.head_sync_s)  # the next drain checkpoints the head
    with caplog.at_level(logging.ERROR, logger="antireplay.audit"):
        assert receiver.receive(signed(msg_id="during")).accepted  # still served
        deadline = time.monotonic() + 30
        while audit.head_failures == 0 and time.monotonic() < deadline:
            time.sleep(0.01)  # the drain runs on the audit writer's thread
    assert audit.head_failures >= 1
    assert any("cannot be written" in r.getMessage() for r in caplog.records)
    behind, failures = _head_behind(metrics)
    assert behind == 1 and failures is not None and failures >= 1
    assert rolled_back(audit) == "AUDIT_HEAD_BEHIND: token removed"
    with sqlite3.connect(tmp_path / "state.db") as db:  # kept until the head vouches for them
        assert db.execute("SELECT count(*) FROM outbox").fetchone()[0] >= 1
    key.down = False
    clock.advance(audit.head_sync_s)
    assert receiver.receive(signed(msg_id="after")).accepted
    audit.drain()
    assert audit.head_behind is None and _head_behind(metrics)[0] == 0
    receiver.close()
    store.close()
    rows = {r.msg_id for r in tail(tmp_path / "audit.db", 20)}
    assert {"before", "during", "after"} <= rows
    report = verify(tmp_path / "audit.db", head_key=key)
    assert report.chain_ok and report.head == "match", report.lines()
