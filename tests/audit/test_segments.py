"""The audit trail as segments: rotation by size and age keeps one chain, retention removes
the oldest whole segments and verify says where it cut; a segment deleted, truncated,
swapped or forged anywhere else is caught, naming the file."""

from __future__ import annotations

import itertools
import logging
import os
import sqlite3
import threading
from pathlib import Path

import pytest
from click.testing import CliRunner

from antireplay.audit import AuditLog, Retention, reanchor, verify
from antireplay.audit.segments import bytes_of, numbered, rotated
from antireplay.cli import main
from antireplay.core.clock import ManualClock
from antireplay.core.errors import AuditFileError, StateUnavailableError
from harness.audit import SMALL_SEGMENT, append, segmented, sql, trail


def rows_of(path: Path) -> list[tuple[int, str, str]]:
    """(seq, prev_hash, hash) of every row of one segment file."""
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return db.execute("SELECT seq, prev_hash, hash FROM audit ORDER BY seq").fetchall()
    finally:
        db.close()


def link_of(path: Path) -> tuple[int, int, str]:
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        n, first, prev = db.execute("SELECT n, first_seq, prev_hash FROM segment").fetchone()
        return int(n), int(first), str(prev)
    finally:
        db.close()


@pytest.fixture
def three(tmp_path: Path) -> Path:
    """A closed trail of 140 rows in at least four segments, nothing removed, the live one
    not empty."""
    path = tmp_path / "audit.db"
    segmented(path, 140).close()
    assert len(rotated(path)) >= 3 and rows_of(path)
    return path


def test_rotation_by_size_keeps_one_chain_across_segments(three: Path) -> None:
    files = [file for _, file in rotated(three)] + [three]
    assert [n for n, _ in rotated(three)] == list(range(1, len(files)))
    for before, after in itertools.pairwise(files):
        last_seq, _, last_hash = rows_of(before)[-1]
        _, first, prev = link_of(after)
        assert (first, prev) == (last_seq + 1, last_hash)  # starts from the previous head
        assert rows_of(after)[0][:2] == (last_seq + 1, last_hash)
        assert bytes_of(before) < 2 * SMALL_SEGMENT
    report = verify(three)
    assert report.ok and report.records == 140 and report.first_segment == 1
    assert report.lines()[0] == f"chain intact to row 140 (140 records in {len(files)} segments)"


def test_rotation_by_age_follows_the_clock(tmp_path: Path) -> None:
    clock = ManualClock(wall=1_800_000_000.0)
    path = tmp_path / "audit.db"
    log = AuditLog(path, clock=clock, retention=Retention(segment_age_s=60.0))
    append(log, 0)
    clock.advance(59.0)
    append(log, 59)
    assert rotated(path) == []  # the live segment's first row is 59 s old
    clock.advance(1.0)
    append(log, 60)  # 60 s old now: this batch is the segment's last
    assert [n for n, _ in rotated(path)] == [1]
    assert [r[0] for r in rows_of(numbered(path, 1))] == [1, 2, 3]
    clock.advance(3600.0)
    append(log, 3660)
    assert [n for n, _ in rotated(path)] == [1]  # a segment's age starts at its first row
    clock.advance(60.0)
    append(log, 3720)
    assert [n for n, _ in rotated(path)] == [1, 2]
    log.close()
    assert verify(path).ok and verify(path).segments == 3


def test_retention_by_bytes_removes_the_oldest_and_verify_reports_the_cut(
    tmp_path: Path,
) -> None:
    path = tmp_path / "audit.db"
    budget = 3 * SMALL_SEGMENT + 8192
    log = segmented(path, 300, Retention(segment_bytes=SMALL_SEGMENT, max_bytes=budget))
    usage = log.usage()
    log.close()
    kept = rotated(path)
    oldest_n, oldest = kept[0]
    assert oldest_n > 1 and usage.bytes <= budget and usage.segments == len(kept) + 1
    first_seq, prev, _ = rows_of(oldest)[0]
    assert link_of(oldest) == (oldest_n, first_seq, prev)
    report = verify(path)
    assert report.ok and (report.first_segment, report.first_row) == (oldest_n, first_seq)
    assert report.records == 300 - first_seq + 1
    said = CliRunner().invoke(main, ["audit", "verify", str(path)])
    assert said.exit_code == 0, said.output
    assert said.output.splitlines()[:2] == [
        f"segments 1–{oldest_n - 1} removed by retention; "
        f"chain verified from row {first_seq} / hash {prev}",
        f"chain intact to row 300 ({report.records} records in {len(kept) + 1} segments)",
    ]
    assert "head checkpoint matches row 300 (MAC verified)" in said.output


def test_retention_by_age_removes_segments_whose_rows_are_all_old(tmp_path: Path) -> None:
    clock = ManualClock(wall=1_800_000_000.0)
    path = tmp_path / "audit.db"
    retention = Retention(segment_bytes=SMALL_SEGMENT, max_age_s=3600.0)
    log = AuditLog(path, clock=clock, retention=retention)
    for i in range(60):
        append(log, i)
    before = [n for n, _ in rotated(path)]
    assert before  # nothing is old yet: every segment kept
    clock.advance(3600.0 + 60)
    for i in range(3700, 3760):  # rows now; the next rotation removes the old segments
        append(log, i)
    log.close()
    left = rotated(path)
    assert left and left[0][0] > max(before)
    assert verify(path).ok and verify(path).first_segment == left[0][0]


def test_usage_counts_every_segment_and_the_oldest_row(three: Path) -> None:
    log = AuditLog(three, retention=Retention(segment_bytes=SMALL_SEGMENT))
    usage = log.usage()
    on_disk = sum(bytes_of(file) for _, file in rotated(three)) + bytes_of(three)
    assert (usage.bytes, usage.segments, usage.oldest) == (
        on_disk, len(rotated(three)) + 1, 1_800_000_000.0,
    )  # fmt: skip
    assert log.count() == 140 and [r.seq for r in log.tail(3)] == [138, 139, 140]
    log.close()


def test_a_single_file_trail_from_before_segments_is_segment_1(tmp_path: Path) -> None:
    path = tmp_path / "audit.db"
    trail(path, 5)
    sql(path, "DROP TABLE segment")  # exactly what an older writer left
    segmented(path, 60).close()
    report = verify(path)
    assert report.ok and report.records == 65 and report.segments > 1
    assert link_of(numbered(path, 2))[0] == 2


def test_rotation_waits_while_another_connection_holds_the_live_segment(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "audit.db"
    log = AuditLog(path, retention=Retention(segment_bytes=SMALL_SEGMENT))
    reader = sqlite3.connect(path)
    try:
        reader.execute("SELECT count(*) FROM audit").fetchone()
        with caplog.at_level(logging.WARNING, "antireplay.audit"):
            for i in range(60):
                append(log, i)
        assert rotated(path) == []  # postponed, every row still written
        assert log.rotations_postponed > 1  # counted each batch, said once
        assert [r.getMessage() for r in caplog.records] == [
            f"audit trail {path}: rotation postponed (another connection has the live "
            "segment open); retried after each batch"
        ]
    finally:
        reader.close()
    rows = 60
    while not rotated(path):  # the reader gone, the next batch past the size rotates
        append(log, rows)
        rows += 1
    log.close()
    assert [n for n, _ in rotated(path)] == [1]
    assert verify(path).ok and verify(path).records == rows


# --- what retention does not do: deletions, truncations, swaps, forgeries ---------------------


def test_deleting_a_middle_segment_is_caught_naming_it(three: Path) -> None:
    numbered(three, 2).unlink()
    for opener in (verify, AuditLog):
        with pytest.raises(AuditFileError, match="segment 2 of the trail is missing") as err:
            opener(three)
        assert err.value.path == str(numbered(three, 2))
        assert "restore it from a backup" in err.value.recovery
    said = CliRunner().invoke(main, ["audit", "verify", str(three)])
    assert said.exit_code == 2 and "audit.db.000002" in " ".join(said.output.split())


def test_deleting_the_newest_rotated_segments_is_not_retention(three: Path) -> None:
    """All rotated segments gone, though retention removed none: the head says so."""
    for _, file in rotated(three):
        file.unlink()
    with pytest.raises(AuditFileError, match="segment 1 of the trail is missing"):
        verify(three)
    with pytest.raises(AuditFileError, match="segment 1 of the trail is missing"):
        AuditLog(three)


def test_deleting_the_oldest_segment_retention_kept_is_caught(tmp_path: Path) -> None:
    path = tmp_path / "audit.db"
    retention = Retention(segment_bytes=SMALL_SEGMENT, max_bytes=3 * SMALL_SEGMENT + 8192)
    segmented(path, 300, retention).close()
    oldest_n, oldest = rotated(path)[0]
    oldest.unlink()
    with pytest.raises(AuditFileError, match=f"segment {oldest_n} of the trail is missing"):
        verify(path)
    # the operator accepts the loss: reanchor records the new oldest segment
    reanchor(path)
    assert verify(path).ok and verify(path).first_segment == oldest_n + 1


def test_truncating_a_rotated_segment_is_caught(three: Path) -> None:
    last = rows_of(numbered(three, 2))[-1][0]
    sql(numbered(three, 2), f"DELETE FROM audit WHERE seq >= {last - 1}")
    report = verify(three)
    assert not report.ok and report.broken_at == last - 1
    assert report.reason == "audit.db.000003 does not start where the segment before it ends"
    with pytest.raises(AuditFileError, match="cannot re-anchor"):
        reanchor(three)


def test_truncating_the_front_of_the_oldest_segment_kept_is_caught(three: Path) -> None:
    """The chain still links from the rows left, but the MACed link says where it starts."""
    for _, file in rotated(three)[:2]:
        file.unlink()
    reanchor(three)  # accept segments 1-2 as gone
    oldest = rotated(three)[0][1]
    first = link_of(oldest)[1]
    sql(oldest, f"DELETE FROM audit WHERE seq < {first + 3}")
    report = verify(three)
    assert (report.broken_at, report.reason) == (
        first, "record missing or reordered (in audit.db.000003)",
    )  # fmt: skip
    # moving the link to the new first row needs the head key
    kept_first = rows_of(oldest)[0]
    sql(oldest, f"UPDATE segment SET first_seq = {kept_first[0]}, prev_hash = '{kept_first[1]}'")
    report = verify(three)
    assert report.broken_at == kept_first[0]
    assert (
        report.reason
        == "audit.db.000003: segment link MAC does not verify (forged, or another key)"
    )


def test_swapping_two_segments_is_caught(three: Path) -> None:
    two, four = numbered(three, 2), numbered(three, 3)
    spare = three.with_name("spare")
    os.rename(two, spare)
    os.rename(four, two)
    os.rename(spare, four)
    with pytest.raises(AuditFileError, match="holds segment 3, not 2: renamed or swapped") as err:
        verify(three)
    assert err.value.path == str(two)
    with pytest.raises(AuditFileError, match="renamed or swapped"):
        AuditLog(three)


def test_reanchor_with_a_new_key_relinks_every_segment(three: Path) -> None:
    three.with_name("audit.db.key").unlink()
    assert verify(three).head == "no-key"
    reanchor(three)  # a new key: the links are MACed again with it
    report = verify(three)
    assert report.ok and report.records == 140
    segmented(three, 10).close()
    assert verify(three).ok


def test_two_writers_in_one_trail_take_turns_rotating(tmp_path: Path) -> None:
    """Neither writer's open connection stops the other's rotation for good: a writer
    whose batch finds rotation due lets its connection go, whoever rotates, the other
    follows the chain into the new live segment."""
    path = tmp_path / "audit.db"
    small = Retention(segment_bytes=SMALL_SEGMENT)
    one, two = AuditLog(path, retention=small), AuditLog(path, retention=small)
    seqs = []
    for i in range(0, 160, 2):
        seqs += [append(one, i), append(two, i + 1)]
    one.close()
    two.close()
    assert seqs == list(range(1, 161))
    assert len(rotated(path)) >= 3
    report = verify(path)
    assert report.ok and report.records == 160, report.lines()


def test_a_trail_replaced_under_two_writers_is_still_refused(tmp_path: Path) -> None:
    """Following a rotation is not adopting any file: one put in the live segment's place
    that is not the rotated one under its numbered name is refused."""
    path = tmp_path / "audit.db"
    one = AuditLog(path, retention=Retention(segment_bytes=SMALL_SEGMENT))
    append(one, 0)
    AuditLog(tmp_path / "other.db").close()
    os.replace(tmp_path / "other.db", path)
    try:
        with pytest.raises(StateUnavailableError, match="deleted or replaced"):
            append(one, 1)
    finally:
        one.close()


def test_a_budget_smaller_than_a_segment_keeps_only_the_live_one(tmp_path: Path) -> None:
    """Retention never removes the live segment, even when it alone is over the budget, and
    the head (the previous segment's last row) still proves the trail."""
    path = tmp_path / "audit.db"
    segmented(path, 100, Retention(segment_bytes=SMALL_SEGMENT, max_bytes=1)).close()
    assert rotated(path) == []
    report = verify(path)
    assert report.ok and report.segments == 1 and report.first_segment > 1
    assert report.last_row == 100


def test_truncating_the_newest_rotated_segment_refuses_the_writer(three: Path) -> None:
    newest = rotated(three)[-1][1]
    last = rows_of(newest)[-1][0]
    sql(newest, f"DELETE FROM audit WHERE seq = {last}")
    with pytest.raises(AuditFileError, match=f"does not start where {newest.name} ends"):
        AuditLog(three)


class PausingLog(AuditLog):
    """A writer that stops in the middle of its first rotation until the test lets it go."""

    def __init__(self, path: Path) -> None:
        self.reached, self.go = threading.Event(), threading.Event()
        super().__init__(path, retention=Retention(segment_bytes=SMALL_SEGMENT))

    def _rotation_point(self, step: str) -> None:
        if step == "prepared" and not self.go.is_set():
            self.reached.set()
            self.go.wait(timeout=30)


def test_a_writer_opening_mid_rotation_waits_for_it(tmp_path: Path) -> None:
    """A second writer (a restarted gateway, ``mavlink-proxy`` on the same trail) started while
    the first is half-way through a rotation neither undoes it nor opens the old segment."""
    path = tmp_path / "audit.db"
    first = PausingLog(path)
    rows = threading.Thread(target=lambda: [append(first, i) for i in range(60)])
    rows.start()
    assert first.reached.wait(timeout=30)
    opened: list[AuditLog] = []
    second = threading.Thread(target=lambda: opened.append(AuditLog(path)))
    second.start()
    second.join(timeout=0.5)
    assert second.is_alive() and not opened  # waits on PATH.lock while the rotation runs
    first.go.set()
    second.join(timeout=30)
    assert opened and [n for n, _ in rotated(path)] == [1]  # the rotation went through whole
    append(opened[0], 1000)  # appends to the new live segment, after the first writer's rows
    opened[0].close()
    rows.join(timeout=30)
    first.close()
    report = verify(path)
    assert report.ok and report.records == 61 and report.segments >= 2


def test_a_head_from_before_the_last_rotation_only_under_claims(tmp_path: Path) -> None:
    """A power cut can bring back a head whose row is now in a rotated segment: the writer
    opens, and verify counts the rows after it as not covered."""
    path = tmp_path / "audit.db"
    head = path.with_name("audit.db.head")
    log = AuditLog(path, retention=Retention(segment_bytes=SMALL_SEGMENT))
    append(log, 0)
    older = head.read_bytes()  # covers row 1
    for i in range(1, 60):
        append(log, i)
    log.close()
    assert len(rotated(path)) >= 2
    head.write_bytes(older)
    report = verify(path)
    assert report.ok and (report.checkpoint_rows, report.after_checkpoint) == (1, 59)
    AuditLog(path).close()  # adopts the rows after it into a new checkpoint
    assert verify(path).after_checkpoint == 0
