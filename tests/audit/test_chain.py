"""The audit row value: one frozen, slotted ``AuditRow`` whose fields are the trail's columns,
the keys its hash covers, and, with ``seq``, what a ``Record`` read back carries."""

from __future__ import annotations

import dataclasses
import sqlite3
from pathlib import Path

import pytest

from antireplay.audit import AuditLog, AuditRow, Record, tail
from antireplay.audit.chain import _FIELDS, ROW_FIELDS


def test_the_row_is_frozen_and_slotted() -> None:
    row = AuditRow(1_800_000_000.0, "accepted")
    with pytest.raises(dataclasses.FrozenInstanceError):
        row.outcome = "rejected"  # type: ignore[misc]
    assert not hasattr(row, "__dict__")
    assert (row.code, row.warning, row.msg_type, row.sender, row.msg_id) == (None,) * 5
    assert row.sender_verified is False


def test_the_fields_are_spelled_once(tmp_path: Path) -> None:
    """The trail's columns, the stored columns and a record's fields all come from AuditRow."""
    assert tuple(f.name for f in dataclasses.fields(AuditRow)) == ROW_FIELDS
    assert ("seq", *ROW_FIELDS) == _FIELDS
    assert {f.name for f in dataclasses.fields(Record)} == set(_FIELDS)
    log = AuditLog(tmp_path / "audit.db")
    log.close()
    with sqlite3.connect(tmp_path / "audit.db") as db:
        columns = [r[1] for r in db.execute("PRAGMA table_info(audit)")]
    db.close()
    assert columns == [*_FIELDS, "prev_hash", "hash"]


def test_a_record_is_the_row_written_plus_its_seq(tmp_path: Path) -> None:
    """What is read back equals what was written (identifiers sanitized), with its seq."""
    written = AuditRow(
        1_800_000_000.5, "rejected", "REPLAY_DETECTED", "QOS_RETRY", 1, "operator", True, "m1"
    )
    hostile = AuditRow(1_800_000_001.0, "rejected", sender="x\x1b[31m", msg_id="m" * 65)
    log = AuditLog(tmp_path / "audit.db")
    try:
        assert log.append(written) == 1
        assert log.append(hostile) == 2
    finally:
        log.close()
    first, second = tail(tmp_path / "audit.db")
    assert isinstance(first, AuditRow)
    assert first == Record(**dataclasses.asdict(written), seq=1)
    assert second.seq == 2 and second.sender is not None and second.msg_id is not None
    assert second.sender.startswith("sha256:") and second.msg_id.startswith("sha256:")
