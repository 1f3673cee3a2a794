"""The ESTOP spill: reserved up front, MAC-chained, merged into the trail by the writer."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import pytest

from antireplay.audit import AuditLog, AuditRow, tail, verify
from antireplay.audit.spill import SLOT, Spill

KEY = bytes(range(32))


def _row(i: int) -> dict[str, Any]:
    """An ESTOP's row as the spill stores it."""
    return {
        "at": 1_800_000_000.0 + i, "outcome": "accepted", "code": None,
        "warning": "AUDIT_UNAVAILABLE", "msg_type": 6, "sender": "operator",
        "sender_verified": 1, "msg_id": f"estop-{i}",
    }  # fmt: skip


def _estop(log: AuditLog, i: int) -> bool:
    return log.spill(AuditRow(**{**_row(i), "sender_verified": True}))


def test_the_file_is_reserved_at_open_and_its_rows_survive_a_reopen(tmp_path: Path) -> None:
    path = tmp_path / "audit.db.spill"
    spill = Spill(path, KEY, slots=8)
    assert os.stat(path).st_blocks * 512 >= SLOT * 9  # allocated, not sparse
    assert all(spill.add(_row(i)) for i in range(8))
    assert not spill.add(_row(8))  # full: the caller keeps it in memory
    spill.close()
    again = Spill(path, KEY, slots=8)
    assert again.pending() == [_row(i) for i in range(8)]
    again.merged(3)
    assert again.pending() == [_row(i) for i in range(3, 8)]
    again.close()
    assert Spill(path, KEY, slots=8).pending() == [_row(i) for i in range(3, 8)]


def test_a_forged_or_moved_slot_is_not_merged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "audit.db.spill"
    spill = Spill(path, KEY, slots=8)
    for i in range(3):
        spill.add(_row(i))
    spill.close()
    raw = bytearray(path.read_bytes())
    second = raw[2 * SLOT : 3 * SLOT]
    raw[2 * SLOT : 3 * SLOT] = second.replace(b'"estop-1"', b'"estop-9"')
    path.write_bytes(bytes(raw))
    with caplog.at_level(logging.ERROR, logger="antireplay.audit"):
        assert Spill(path, KEY, slots=8).pending() == [_row(0)]
    assert "slot 2: MAC does not verify" in caplog.text


def test_a_spill_of_another_key_is_moved_aside_as_evidence(tmp_path: Path) -> None:
    path = tmp_path / "audit.db.spill"
    spill = Spill(path, KEY, slots=4)
    spill.add(_row(0))
    spill.close()
    fresh = Spill(path, bytes(32), slots=4)
    assert fresh.pending() == []
    assert [p.name.split("-")[0] for p in tmp_path.glob("audit.db.spill.unverified-*")] == [
        "audit.db.spill.unverified"
    ]


def test_spilled_rows_are_merged_chained_with_the_next_batch(tmp_path: Path) -> None:
    log = AuditLog(tmp_path / "audit.db")
    try:
        assert _estop(log, 0) and _estop(log, 1) and log.spilled == 2
        log.append(AuditRow(
            at=1_800_000_010.0, outcome="accepted", code=None, warning=None, msg_type=1,
            sender="operator", sender_verified=True, msg_id="after",
        ))  # fmt: skip
        assert log.spilled == 0
        assert [r.msg_id for r in log.tail(5)] == ["estop-0", "estop-1", "after"]
    finally:
        log.close()
    assert verify(tmp_path / "audit.db").ok


def test_spilled_rows_are_merged_at_the_next_start_after_the_trail_is_restored(
    tmp_path: Path,
) -> None:
    """The trail deleted under its writer: rows spill; restored from a backup, the next
    start merges them, chained."""
    trail, backup = tmp_path / "audit.db", tmp_path / "backup.db"
    log = AuditLog(trail)
    log.append(AuditRow(
        at=1_800_000_000.0, outcome="accepted", code=None, warning=None, msg_type=1,
        sender="operator", sender_verified=True, msg_id="before",
    ))  # fmt: skip
    log.close()
    backup.write_bytes(trail.read_bytes())
    log = AuditLog(trail)
    trail.unlink()
    with pytest.raises(Exception, match="deleted or replaced"):
        log.append(AuditRow(
            at=1_800_000_001.0, outcome="accepted", code=None, warning=None, msg_type=1,
            sender="operator", sender_verified=True, msg_id="lost",
        ))  # fmt: skip
    assert _estop(log, 1)
    log.close()
    backup.rename(trail)
    reopened = AuditLog(trail)
    try:
        assert reopened.spilled == 0
        assert [r.msg_id for r in reopened.tail(5)] == ["before", "estop-1"]
    finally:
        reopened.close()
    assert verify(trail).ok


def test_spilled_rows_are_merged_at_close_when_the_trail_takes_them(tmp_path: Path) -> None:
    log = AuditLog(tmp_path / "audit.db")
    assert _estop(log, 0)
    log.close()
    assert [r.msg_id for r in tail(tmp_path / "audit.db")] == ["estop-0"]
    reopened = AuditLog(tmp_path / "audit.db")
    assert reopened.spilled == 0 and reopened.count() == 1
    reopened.close()
