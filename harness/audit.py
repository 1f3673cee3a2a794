"""Audit trails written for a test, and raw SQL on them (what an attacker with the file can do)."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from antireplay.audit import AuditLog, AuditRow, Retention


def trail(path: Path, rows: int) -> None:
    """A closed trail at ``path`` of ``rows`` accepted records, a second apart."""
    log = AuditLog(path)
    for i in range(rows):
        log.append(AuditRow(
            at=1_800_000_000.0 + i, outcome="accepted", code=None, warning=None, msg_type=1,
            sender="op", sender_verified=True, msg_id=f"m{i}",
        ))  # fmt: skip
    log.close()


def sql(path: Path, *statements: str) -> None:
    """Statements run on the file directly, bypassing the writer and its chain."""
    db = sqlite3.connect(path)
    for statement in statements:
        db.execute(statement)
    db.commit()
    db.close()


#: A segment size that rotates the live segment every couple of dozen rows (8 SQLite pages).
SMALL_SEGMENT = 32_768


def append(log: AuditLog, i: int) -> int:
    """One accepted record ``m<i>`` at second ``i`` of the test's epoch."""
    return log.append(AuditRow(
        at=1_800_000_000.0 + i, outcome="accepted", code=None, warning=None, msg_type=1,
        sender="op", sender_verified=True, msg_id=f"m{i}",
    ))  # fmt: skip


def segmented(path: Path, rows: int, retention: Retention | None = None) -> AuditLog:
    """An open writer on ``path`` that rotated while ``rows`` records were appended."""
    log = AuditLog(path, retention=retention or Retention(segment_bytes=SMALL_SEGMENT))
    for i in range(rows):
        append(log, i)
    return log
