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
* **Epochs.**  Ids count within one database: a new one (deleted, replaced) starts
  again at 1.  So the outbox has a random ``epoch`` and the trail's mark names it; a mark
  of another epoch counts as nothing moved.  A database found *behind* the mark (its
  highest id ever below it: a restored copy) gets a new epoch at the drain's start, so
  the rows it puts from then on are moved, never skipped.
* **The trail's head, kept here too.**  Each deletion carries the trail's head as the
  writer made it durable (rows, last hash, oldest segment kept, MACed with the trail's
  head key) into table ``trail_head``, in the same transaction: a trail later found
  behind that record, or holding another hash at its row, was rolled back
  (:mod:`antireplay.audit.consistency`).
* **One trip for an accepted command** (:class:`Paired`): its seen-set record and its
  row are ONE operation: the writer records the entry and, in the same transaction, puts
  the row that ``row(seen)`` returns (``None``: the commit did not accept it, no row), so
  the batch's one fsync makes both durable and the caller is answered once.
"""

from __future__ import annotations

import asyncio
import json
import sqlite3
import uuid
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Protocol, TypeVar

from antireplay.core.window import Seen

T = TypeVar("T")

SCHEMA: Final = """
CREATE TABLE IF NOT EXISTS outbox (id INTEGER PRIMARY KEY AUTOINCREMENT, row TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS outbox_epoch (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    epoch TEXT NOT NULL
);
INSERT OR IGNORE INTO outbox_epoch VALUES (1, lower(hex(randomblob(16))));
CREATE TABLE IF NOT EXISTS trail_head (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    rows INTEGER NOT NULL,
    hash TEXT NOT NULL,
    first INTEGER NOT NULL,
    mac TEXT NOT NULL
);
"""
#: Where the trail stands in one outbox: its epoch and the highest id moved.
Mark = tuple[str | None, int]
#: The trail's head as its writer made it durable: rows, last hash, oldest segment kept, MAC.
TrailHead = tuple[int, str, int, str]
_HEAD_SELECT = "SELECT rows, hash, first, mac FROM trail_head"


@dataclass(frozen=True, slots=True)
class Put:
    """One audit row for the outbox; ``durable``: its batch commits with an fsync."""

    row: str
    durable: bool

    def apply(self, db: sqlite3.Connection) -> int:
        return int(db.execute("INSERT INTO outbox (row) VALUES (?)", (self.row,)).lastrowid or 0)


@dataclass(frozen=True, slots=True)
class Paired:
    """A seen-set commit (key, expires_at, now, force) and the audit row of its acceptance:
    ``row(seen)``, called by the writer inside the transaction with what the commit found,
    is the row's JSON text to put, or ``None`` (not accepted: no row).  Always fsynced."""

    record: tuple[str, float, float, bool]
    row: Callable[[Seen], str | None]
    durable: bool = True


@dataclass(frozen=True, slots=True)
class Forget:
    """Delete the rows up to ``mark`` (if still of its epoch): the trail holds them durably
    (and record its ``head``, if given, in the same transaction)."""

    mark: Mark
    durable: bool = False
    head: TrailHead | None = None

    def apply(self, db: sqlite3.Connection) -> int:
        epoch, upto = self.mark
        if self.head is not None:
            db.execute("INSERT OR REPLACE INTO trail_head VALUES (1, ?, ?, ?, ?)", self.head)
        return db.execute(
            "DELETE FROM outbox WHERE id <= ? AND (SELECT epoch FROM outbox_epoch) = ?",
            (upto, epoch),
        ).rowcount


@dataclass(frozen=True, slots=True)
class Renew:
    """Start a new epoch: the trail's mark no longer applies to this database."""

    epoch: str
    durable: bool = True

    def apply(self, db: sqlite3.Connection) -> int:
        return db.execute("UPDATE outbox_epoch SET epoch = ?", (self.epoch,)).rowcount


class Host(Protocol):
    """What the outbox needs of its store (:class:`~antireplay.state.sqlite.SqliteStore`)."""

    path: Path

    def enqueue_outbox(self, op: Put | Forget | Renew) -> Future[int]: ...

    def enqueue_outbox_async(self, op: Put) -> asyncio.Future[int]: ...

    def read_outbox(self, query: Callable[[sqlite3.Connection], T]) -> T: ...

    def defer_commits(self) -> None: ...


class Outbox:
    """A SQLite store's outbox: rows in through its committer, out to the audit writer."""

    def __init__(self, store: Host) -> None:
        self.store = store
        #: Called on the store's writer thread after a batch that put rows (wakes a drain).
        self.on_rows: Callable[[], None] | None = None
        #: Whether the trail draining this outbox is still there (its live segment not
        #: deleted): asked once per batch holding paired rows, on the writer thread; a
        #: batch that finds it gone puts none of them (``None``: not asked).
        self.trail_there: Callable[[], bool] | None = None

    def put(self, row: dict[str, Any], *, durable: bool) -> Future[int]:
        """Queue ``row``; the future completes once it is committed (durably if asked)."""
        return self.store.enqueue_outbox(Put(json.dumps(row), durable))

    def put_async(self, row: dict[str, Any], *, durable: bool) -> asyncio.Future[int]:
        """:meth:`put` from a running event loop (no thread held)."""
        return self.store.enqueue_outbox_async(Put(json.dumps(row), durable))

    def pending(self, mark: Mark, limit: int) -> tuple[str, list[tuple[int, dict[str, Any]]]]:
        """This outbox's epoch and its committed rows above ``mark``, oldest first (at most
        ``limit``; all of them if the mark is of another epoch)."""

        def query(db: sqlite3.Connection) -> tuple[str, list[tuple[int, dict[str, Any]]]]:
            (epoch,) = db.execute("SELECT epoch FROM outbox_epoch").fetchone()
            after = mark[1] if mark[0] == epoch else 0
            found = db.execute(
                "SELECT id, row FROM outbox WHERE id > ? ORDER BY id LIMIT ?", (after, limit)
            ).fetchall()
            return str(epoch), [(int(i), json.loads(text)) for i, text in found]

        return self.store.read_outbox(query)

    def behind(self, mark: Mark) -> bool:
        """Whether this database never reached ``mark`` of its own epoch (a restored copy)."""

        def query(db: sqlite3.Connection) -> bool:
            (epoch,) = db.execute("SELECT epoch FROM outbox_epoch").fetchone()
            top = db.execute("SELECT seq FROM sqlite_sequence WHERE name = 'outbox'").fetchone()
            return mark[0] == epoch and (0 if top is None else int(top[0])) < mark[1]

        return self.store.read_outbox(query)

    def renew(self) -> Future[int]:
        """Give the outbox a new epoch (its rows are all moved again, none skipped)."""
        return self.store.enqueue_outbox(Renew(uuid.uuid4().hex))

    def forget(self, mark: Mark, head: TrailHead | None = None) -> Future[int]:
        """Delete the rows up to ``mark`` with the store's next batch (no fsync of its own),
        recording the trail's ``head`` in the same transaction."""
        return self.store.enqueue_outbox(Forget(mark, head=head))

    def trail_head(self) -> TrailHead | None:
        """The trail's head as last recorded here (``None``: never recorded)."""
        return self.store.read_outbox(_trail_head)

    def flush(self) -> None:
        """Return once every row queued so far is committed (the writer's queue is FIFO)."""
        self.forget((None, 0)).result()

    def count(self) -> int:
        """Rows waiting to be moved (or moved but not yet durable in the trail)."""
        return self.store.read_outbox(
            lambda db: int(db.execute("SELECT count(*) FROM outbox").fetchone()[0])
        )


def _trail_head(db: sqlite3.Connection) -> TrailHead | None:
    try:
        row = db.execute(_HEAD_SELECT).fetchone()
    except sqlite3.OperationalError:  # a database from before the record: nothing recorded
        return None
    if row is None:
        return None
    rows, digest, first, mac = row
    if not (type(rows) is int and isinstance(digest, str) and type(first) is int
            and isinstance(mac, str)):  # fmt: skip
        raise sqlite3.DatabaseError("its trail_head row is not one antireplay writes")
    return rows, digest, first, mac


def read_trail_head(path: Path) -> TrailHead | None:
    """The trail's head recorded in the SQLite state database at ``path``, read-only
    (``audit verify --state``); a file that is not one raises ``sqlite3.DatabaseError``."""
    db = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
    try:
        db.execute("SELECT count(*) FROM sqlite_master").fetchone()
        return _trail_head(db)
    finally:
        db.close()
