"""The audit trail: append-only, hash-chained records in SQLite; never the payload.

Theory of operation
-------------------
Every accepted message and every rejection that matters is one row:
time, outcome, code, warning, message type, sender (the authenticated owner,
or the claimed ``sender`` marked unverified) and a sanitized msg_id.  Attacker
strings are never stored raw: an identifier is kept only if it is at most 64
characters of ``[A-Za-z0-9._:@/-]``; anything else is replaced by
``sha256:<first 16 hex>`` of it, so no log line can be forged with newlines,
escapes or terminal codes, and nothing from ``params`` is ever written.

Each row stores ``hash = SHA-256(prev_hash | canonical JSON of the row)``; the
first row chains from 64 zeros.  :func:`verify` recomputes the chain and
reports the first broken link, so an edited, deleted or reordered row is
detected.  Writes use WAL with ``synchronous=FULL``: ``append`` returns after
the record is durable, so a crash never loses a committed record.
"""

from __future__ import annotations

import hashlib
import json
import re
import sqlite3
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from antireplay.errors import StateUnavailableError

GENESIS = "0" * 64
_SAFE = re.compile(r"[A-Za-z0-9._:@/-]{1,64}")
_SCHEMA = """
CREATE TABLE IF NOT EXISTS audit (
    seq INTEGER PRIMARY KEY,
    at REAL NOT NULL,
    outcome TEXT NOT NULL,
    code TEXT,
    warning TEXT,
    msg_type INTEGER,
    sender TEXT,
    sender_verified INTEGER NOT NULL,
    msg_id TEXT,
    prev_hash TEXT NOT NULL,
    hash TEXT NOT NULL
);
"""
_FIELDS = (
    "seq",
    "at",
    "outcome",
    "code",
    "warning",
    "msg_type",
    "sender",
    "sender_verified",
    "msg_id",
)
_COLUMNS = ",".join(_FIELDS)  # constants only: no user input ever reaches SQL text
_TAIL = f"SELECT {_COLUMNS} FROM audit ORDER BY seq DESC LIMIT ?"  # noqa: S608
_ALL = f"SELECT {_COLUMNS}, prev_hash, hash FROM audit ORDER BY seq"  # noqa: S608


def sanitize(value: object) -> str | None:
    """An identifier safe to store and print; anything suspicious becomes a short hash."""
    if value is None:
        return None
    text = value if isinstance(value, str) else repr(value)
    if _SAFE.fullmatch(text):
        return text
    return "sha256:" + hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()[:16]


def _digest(prev: str, row: dict[str, Any]) -> str:
    body = json.dumps(row, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256((prev + body).encode()).hexdigest()


@dataclass(frozen=True)
class Record:
    """One audit row, as returned by :meth:`AuditLog.tail`."""

    seq: int
    at: float
    outcome: str
    code: str | None
    warning: str | None
    msg_type: int | None
    sender: str | None
    sender_verified: bool
    msg_id: str | None


class AuditLog:
    """Append-only, hash-chained audit trail in one SQLite file."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.executescript(_SCHEMA)
        self._lock = threading.Lock()

    def append(
        self,
        *,
        at: float,
        outcome: str,
        code: str | None,
        warning: str | None,
        msg_type: int | None,
        sender: object,
        sender_verified: bool,
        msg_id: object,
    ) -> int:
        """Durably append one record; returns its sequence number.

        Raises ``STATE_UNAVAILABLE`` when the record cannot be made durable (disk full,
        closed database): callers must not act on a message they could not audit.
        """
        row: dict[str, Any] = {
            "at": at,
            "outcome": outcome,
            "code": code,
            "warning": warning,
            "msg_type": msg_type,
            "sender": sanitize(sender),
            "sender_verified": int(sender_verified),
            "msg_id": sanitize(msg_id),
        }
        try:
            return self._write(row)
        except (sqlite3.Error, OSError) as exc:
            raise StateUnavailableError(f"audit trail unavailable: {exc}") from None

    def _write(self, fields: dict[str, Any]) -> int:
        """Chain and commit one row in a single write transaction."""
        with self._lock:
            db = self._db
            db.execute("BEGIN IMMEDIATE")
            try:
                last = db.execute(
                    "SELECT seq, hash FROM audit ORDER BY seq DESC LIMIT 1"
                ).fetchone()
                seq, prev = (1, GENESIS) if last is None else (last[0] + 1, last[1])
                row = {"seq": seq, **fields}
                db.execute(
                    "INSERT INTO audit VALUES (?,?,?,?,?,?,?,?,?,?,?)",
                    (*(row[f] for f in _FIELDS), prev, _digest(prev, row)),
                )
                db.execute("COMMIT")
            except BaseException:
                db.execute("ROLLBACK")
                raise
            return seq

    def tail(self, n: int = 20) -> list[Record]:
        with self._lock:
            rows = self._db.execute(_TAIL, (n,)).fetchall()
        return [
            Record(r[0], r[1], r[2], r[3], r[4], r[5], r[6], bool(r[7]), r[8])
            for r in reversed(rows)
        ]

    def count(self) -> int:
        with self._lock:
            return int(self._db.execute("SELECT count(*) FROM audit").fetchone()[0])

    def close(self) -> None:
        with self._lock:
            self._db.close()


@dataclass(frozen=True)
class ChainReport:
    """Result of :func:`verify`: how many records, and the first broken link if any."""

    records: int
    broken_at: int | None
    reason: str | None

    @property
    def ok(self) -> bool:
        return self.broken_at is None


def verify(path: str | Path) -> ChainReport:
    """Recompute the hash chain; report the first record that does not link."""
    db = sqlite3.connect(f"file:{Path(path)}?mode=ro", uri=True)
    try:
        cursor = db.execute(_ALL)
        prev, expected_seq, count = GENESIS, 1, 0
        for values in cursor:
            count += 1
            row = dict(zip(_FIELDS, values[:9], strict=True))
            if row["seq"] != expected_seq:
                return ChainReport(count, expected_seq, "record missing or reordered")
            if values[9] != prev:
                return ChainReport(count, row["seq"], "prev_hash does not link")
            if values[10] != _digest(prev, row):
                return ChainReport(count, row["seq"], "record contents changed")
            prev, expected_seq = values[10], expected_seq + 1
        return ChainReport(count, None, None)
    finally:
        db.close()
