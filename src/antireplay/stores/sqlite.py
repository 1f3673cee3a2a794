"""SqliteStore: replay state on one machine that survives kill -9 and reboots.

WAL journal with ``synchronous=FULL``: a ``record`` returns only after its
commit is durable, so a message accepted before a crash is still remembered
after it.  Several processes may share one file; SQLite's write lock makes
``record`` and ``advance`` atomic across them (``busy_timeout`` waits for the
lock instead of failing).  Expired rows are purged a few at a time on every
write (bounded work per call), so the file stays bounded by the live set.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

from antireplay.errors import StateUnavailableError
from antireplay.stores import _codec

T = TypeVar("T")
PURGE_BATCH = 32
_SCHEMA = """
CREATE TABLE IF NOT EXISTS seen (key TEXT PRIMARY KEY, expires REAL NOT NULL) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS seen_expires ON seen (expires);
CREATE TABLE IF NOT EXISTS counters (key TEXT PRIMARY KEY, value TEXT NOT NULL) WITHOUT ROWID;
"""
_RECORD = """
INSERT INTO seen (key, expires) VALUES (?, ?)
ON CONFLICT (key) DO UPDATE SET expires = excluded.expires WHERE seen.expires < ?
"""
_PURGE = """
DELETE FROM seen WHERE key IN (SELECT key FROM seen WHERE expires < ? ORDER BY expires LIMIT ?)
"""
_ADVANCE = """
INSERT INTO counters (key, value) VALUES (?, ?)
ON CONFLICT (key) DO UPDATE SET value = excluded.value WHERE excluded.value > counters.value
"""


class SqliteStore:
    """The store contract on a SQLite file (WAL, synchronous commits)."""

    persistent = True

    def __init__(self, path: str | Path, *, timeout_s: float = 10.0) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = self._open(timeout_s)
        self._lock = threading.Lock()

    def _open(self, timeout_s: float) -> sqlite3.Connection:
        """Connect and set up; processes opening one new file at once may briefly collide.

        Switching to WAL and creating the schema need the write lock, and SQLite can
        answer "database is locked" at once instead of waiting, so setup is retried.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                db = sqlite3.connect(
                    self.path, timeout=timeout_s, isolation_level=None, check_same_thread=False
                )
                db.execute("PRAGMA journal_mode=WAL")
                db.execute("PRAGMA synchronous=FULL")
                db.executescript(_SCHEMA)
                return db
            except sqlite3.OperationalError as exc:
                if "locked" not in str(exc) or time.monotonic() > deadline:
                    raise StateUnavailableError(f"cannot open {self.path}: {exc}") from None
                time.sleep(0.01)
            except sqlite3.Error as exc:
                raise StateUnavailableError(f"cannot open {self.path}: {exc}") from None

    def fence(self) -> float:
        return float("-inf")

    def lookup(self, key: str) -> float | None:
        found = self._fetch("SELECT expires FROM seen WHERE key = ?", (key,))
        return None if found is None else float(found[0])

    def record(self, key: str, expires_at: float, now: float) -> bool:
        return self.record_many([(key, expires_at)], now)[0]

    def record_many(self, items: Sequence[tuple[str, float]], now: float) -> list[bool]:
        def tx() -> list[bool]:
            db = self._db
            db.execute("BEGIN IMMEDIATE")
            try:
                db.execute(_PURGE, (now, PURGE_BATCH))
                results = [db.execute(_RECORD, (k, e, now)).rowcount == 1 for k, e in items]
                db.execute("COMMIT")
            except BaseException:
                db.execute("ROLLBACK")
                raise
            return results

        with self._lock:
            return self._run(tx)

    def advance(self, key: str, value: int) -> bool:
        encoded = _codec.encode(value)

        def tx() -> bool:
            return self._db.execute(_ADVANCE, (key, encoded)).rowcount == 1

        with self._lock:
            return self._run(tx)

    def current(self, key: str) -> int | None:
        row = self._fetch("SELECT value FROM counters WHERE key = ?", (key,))
        return None if row is None else _codec.decode(str(row[0]))

    def count(self) -> int:
        """Rows in the seen-set (live and not yet purged)."""
        row = self._fetch("SELECT count(*) FROM seen", ())
        return 0 if row is None else int(row[0])

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def _fetch(self, sql: str, params: tuple[object, ...]) -> tuple[Any, ...] | None:
        def query() -> tuple[Any, ...] | None:
            row: tuple[Any, ...] | None = self._db.execute(sql, params).fetchone()
            return row

        with self._lock:
            return self._run(query)

    @staticmethod
    def _run(op: Callable[[], T]) -> T:
        try:
            return op()
        except sqlite3.Error as exc:
            raise StateUnavailableError(f"sqlite: {exc}") from None
