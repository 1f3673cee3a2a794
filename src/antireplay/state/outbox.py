"""The audit outbox: audit rows written in the replay state's own transactions.

Theory of operation
-------------------
An accepted message needs two things durable before it is answered: its seen-set entry
and its audit row.  In two files that costs two fsyncs in a row (three with the store's
witness).  The outbox makes it one: the row goes into table ``outbox`` of the SQLite
state database, through the store's one group committer, so the entry and the row (and
every other caller's of that batch) are made durable by one WAL fsync.

* **Who waits for what.**  A row is ``durable`` (an accepted message, a loss, anything
  a caller blocks on) or not (a refusal).  A batch holding a durable row commits with
  ``synchronous=FULL``; the others, and the seen-set commits the outbox defers
  (:meth:`~antireplay.state.sqlite.SqliteStore.defer_commits`), commit with ``NORMAL``:
  written to the OS (a ``kill -9`` loses nothing) and made durable by the next FULL
  commit, whose WAL fsync covers every frame before it.  A deferred entry is only
  believed by refusals until then, and its message is answered only once its own
  accepted row, queued after it, is durable.
* **Moved, then forgotten.**  The audit writer (:mod:`antireplay.audit.writer`) moves
  rows into the chained trail in id order and records the highest id it moved in the
  trail, in the same transaction (no row is moved twice, whichever process drains);
  once the trail's copy is durable it deletes them here (:meth:`Outbox.forget`).  Ids
  are ``AUTOINCREMENT``: never reused, and committed in increasing order under the
  database's write lock, so several processes sharing one file drain one sequence.
"""

from __future__ import annotations

import asyncio
import json
import sqlite3
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

if TYPE_CHECKING:
    from antireplay.state.sqlite import SqliteStore

SCHEMA: Final = (
    "CREATE TABLE IF NOT EXISTS outbox (id INTEGER PRIMARY KEY AUTOINCREMENT, row TEXT NOT NULL)"
)


@dataclass(frozen=True, slots=True)
class Put:
    """One audit row for the outbox; ``durable``: its batch commits with an fsync."""

    row: str
    durable: bool

    def apply(self, db: sqlite3.Connection) -> int:
        return int(db.execute("INSERT INTO outbox (row) VALUES (?)", (self.row,)).lastrowid or 0)


@dataclass(frozen=True, slots=True)
class Forget:
    """Delete the rows up to ``upto``: the trail holds them durably."""

    upto: int
    durable: bool = False

    def apply(self, db: sqlite3.Connection) -> int:
        return db.execute("DELETE FROM outbox WHERE id <= ?", (self.upto,)).rowcount


class Outbox:
    """A SQLite store's outbox: rows in through its committer, out to the audit writer."""

    def __init__(self, store: SqliteStore) -> None:
        self.store = store
        #: Called on the store's writer thread after a batch that put rows (wakes a drain).
        self.on_rows: Callable[[], None] | None = None

    def put(self, row: dict[str, Any], *, durable: bool) -> Future[int]:
        """Queue ``row``; the future completes once it is committed (durably if asked)."""
        return self.store.enqueue_outbox(Put(json.dumps(row), durable))

    def put_async(self, row: dict[str, Any], *, durable: bool) -> asyncio.Future[int]:
        """:meth:`put` from a running event loop (no thread held)."""
        return self.store.enqueue_outbox_async(Put(json.dumps(row), durable))

    def pending(self, after: int, limit: int) -> list[tuple[int, dict[str, Any]]]:
        """Committed rows with an id above ``after``, oldest first (at most ``limit``)."""

        def query(db: sqlite3.Connection) -> list[tuple[int, dict[str, Any]]]:
            found = db.execute(
                "SELECT id, row FROM outbox WHERE id > ? ORDER BY id LIMIT ?", (after, limit)
            ).fetchall()
            return [(int(i), json.loads(text)) for i, text in found]

        return self.store.read_outbox(query)

    def forget(self, upto: int) -> Future[int]:
        """Delete the rows up to ``upto`` with the store's next batch (no fsync of its own)."""
        return self.store.enqueue_outbox(Forget(upto))

    def count(self) -> int:
        """Rows waiting to be moved (or moved but not yet durable in the trail)."""
        return self.store.read_outbox(
            lambda db: int(db.execute("SELECT count(*) FROM outbox").fetchone()[0])
        )
