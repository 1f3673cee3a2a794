"""SqliteStore: replay state on one machine that survives kill -9 and reboots, and notices loss.

Size: one file on purpose: the open-time loss detection, the witness and the commit
path share one SQLite connection and one lock, and splitting them would spread that
invariant across modules.

Theory of operation
-------------------
WAL journal with ``synchronous=FULL``: a ``commit`` returns only after its
transaction is durable, so a message accepted before a crash is still
remembered after it.  Commits are **group-committed**
(:mod:`antireplay.state.groupcommit`): concurrent callers' records share one
transaction and one WAL fsync, each caller answered once its own record is
durable.  With an audit outbox (:mod:`.outbox`) the batch also carries audit rows,
and entries may be *deferred* (``synchronous=NORMAL``) to the accepted row that
follows each, whose batch's fsync covers both: one fsync per batch, not three.
Several processes may share one file; SQLite's write lock (``BEGIN IMMEDIATE``)
makes each batch and ``advance`` atomic across them.  A fresh ESTOP's commit waits for
that lock at most :data:`SAFETY_WAIT_S` (not the busy timeout): past it, the ESTOP is
delivered flagged ``STATE_UNAVAILABLE`` while its record stays queued, committed once the
lock frees (another process holding it, even stopped, never delays an ESTOP).  Other
operations wait up to the busy timeout once; after a wait that ran out, each fails
after :data:`STALLED_WAIT_S` until a transaction begins again (no pile-up of timeouts).

* **Entries live to their own expiry; early removal raises the watermark.**
  Each commit purges at most ``PURGE_BATCH`` rows whose expiry is below the
  caller's ``now`` and raises the persisted watermark (table ``meta``) to the
  largest expiry it removed, in the same transaction.  A purge that runs while
  the wall clock has stepped forward therefore never re-opens a replay when
  the clock steps back.
* **A lost, truncated, replaced or rolled-back file is detected.**  Beside the
  database lives a small **witness** file (``<db>.witness``): a deployment id
  and a generation (plus the highest wall time of any commit), rewritten in
  place after each durable COMMIT with the generation that COMMIT made durable,
  and ``fdatasync``-ed at most every :data:`WITNESS_SYNC_S` (and at open and
  close).  So it is never ahead of the database, not even after a power cut (no
  false alarm); a ``kill -9`` loses nothing written; a power cut may leave it an
  older genuine generation, which only under-claims: a copy restored between the
  two is what the anchor (below) is for.
  Its name is hidden (``.state.db.witness``) so that ``rm state.db*`` does not
  take it along.  While running, a database whose generation falls below the
  one this process last wrote was rolled back under it (a live restore): also
  a fence.  The database's ``meta`` row carries the
  same two values.  At open:

  ==========================================  =====================================
  what is found                               what it means / what happens
  ==========================================  =====================================
  neither database nor witness                a new deployment: created, no fence
  witness, database missing or empty          deleted or truncated: **fence**
  witness of another deployment               the file was replaced: **fence**
  database generation below the witness's     rolled back (a restored copy): **fence**
  database with state but no witness          witness lost (or made by an older
                                              version): **fence**
  with an anchor (:mod:`.anchor`, outside     a restored copy of the whole directory
  the directory), any one copy: the database  or an anchor copy lost: **fence** (a lazy
  behind it, of another deployment, missing,  anchor also raises a restart fence to
  or no copy for existing state               its lease's end, said as a fence)
  an anchor file of another state             refused at start (``StateFileError``)
  an anchor that cannot be reached            opened unverified: lookups, commits and
                                              readiness refused until it answers
  a file that is not a readable database,     refused at start (``StateFileError``
  or a stored value that does not decode      names the file and the recovery:
  (a hand-edited row)                         move it aside; the next start fences)
  ==========================================  =====================================

  A fence is the wall time at which the loss was noticed (no lower than the
  witness's highest commit time, in case the clock stepped back), persisted in
  ``meta``; the window refuses anything stamped at or before ``fence + skew``,
  which covers every message the lost state could have held, and counts it
  (``data_loss_events``).

Deleting the database *and* its witness is indistinguishable from a new
deployment; that is the documented way to reset.  Corruption found while
running answers ``STATE_UNAVAILABLE`` (503; a fresh ESTOP still passes) and
names the file and the recovery; so does a lookup or commit that reads a value
that does not decode, and a database deleted or replaced while running (each
write transaction first checks that the path still names the file it opened),
until the restart that fences.  Readers open the existing file
only (``mode=rw``): a lookup or a readiness probe never creates a new empty one.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import sqlite3
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from pathlib import Path
from typing import Any, Final, TypeVar, cast

from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import StateFileError, StateUnavailableError
from antireplay.core.window import NEVER, Seen
from antireplay.state import _codec
from antireplay.state.anchor import Anchored, AnchorUnavailableError, Read, StateAnchor
from antireplay.state.contract import Offload
from antireplay.state.durable import Witness, file_identity
from antireplay.state.groupcommit import GroupCommitter
from antireplay.state.outbox import SCHEMA as _OUTBOX_SCHEMA
from antireplay.state.outbox import Forget, Outbox, Put, Renew

T = TypeVar("T")
log = logging.getLogger("antireplay.state.sqlite")
PURGE_BATCH: Final = 32
_SCHEMA = """
CREATE TABLE IF NOT EXISTS seen (key TEXT PRIMARY KEY, expires REAL NOT NULL) WITHOUT ROWID;
CREATE INDEX IF NOT EXISTS seen_expires ON seen (expires);
CREATE TABLE IF NOT EXISTS counters (key TEXT PRIMARY KEY, value TEXT NOT NULL) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS meta (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    deployment TEXT NOT NULL,
    generation INTEGER NOT NULL,
    watermark REAL NOT NULL,
    fence REAL NOT NULL,
    data_loss_events INTEGER NOT NULL
);
"""
_PURGE_SELECT = "SELECT key, expires FROM seen WHERE expires < ? ORDER BY expires LIMIT ?"
_ADVANCE = """
INSERT INTO counters (key, value) VALUES (?, ?)
ON CONFLICT (key) DO UPDATE SET value = excluded.value WHERE excluded.value > counters.value
"""
_META_SELECT = "SELECT deployment, generation, watermark, fence, data_loss_events FROM meta"
#: Stored expiries that are not numbers: SQLite orders every number before any text or
#: blob, so the index finds them at once (a REAL column keeps what it cannot convert).
_SEEN_UNDECODABLE = "SELECT key, expires FROM seen WHERE expires >= '' LIMIT 1"
#: One queued seen-set commit: key, expires_at, now, force.
_Record = tuple[str, float, float, bool]
#: What the writer takes: a seen-set commit or an outbox row (or its deletion).
_Op = _Record | Put | Forget | Renew
#: How long a fresh ESTOP's commit waits for the write lock before it is delivered anyway.
SAFETY_WAIT_S: Final = 0.2
#: How long a transaction waits for the write lock after a wait ran out (see ``_begin``).
STALLED_WAIT_S: Final = 0.05
#: How long the witness may go without an fdatasync while commits move it (see docstring).
WITNESS_SYNC_S: Final = 1.0
#: The meta row as a transaction read it: generation, watermark, fence, data-loss events.
_Meta = tuple[int, float, float, int]
#: The whole meta row, decoded: deployment id, then :data:`_Meta`.
_MetaRow = tuple[str, int, float, float, int]
_FLOOR = -1e300  # SQLite REAL has no -inf literal that round-trips everywhere: "nothing yet"


class SqliteStore:
    """The store contract on a SQLite file (WAL, synchronous commits, witness file)."""

    backend: Final = "sqlite"

    def __init__(
        self,
        path: str | Path,
        *,
        timeout_s: float = 10.0,
        clock: Clock | None = None,
        anchor: StateAnchor | None = None,
    ) -> None:
        self.path = Path(path)
        self.anchor = anchor
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # A hidden name on purpose: ``rm state.db*`` must not take the witness with it.
        self.witness = Witness(self.path.with_name(f".{self.path.name}.witness"))
        self._clock = resolve(clock)
        self._lock = threading.Lock()
        self._timeout_s = timeout_s
        self._stalled = False  # the last wait for the write lock ran out (see _begin)
        self._db = self._open(timeout_s)
        check_readable(self.path)  # stored values that do not decode refuse the start
        self._file = file_identity(self.path)
        self._deployment = ""
        self._generation = 0
        self._wall_hw = _FLOOR
        self._witness_synced: float | None = None
        self._opened = False
        self._lost_pending = False
        self._watermark = NEVER
        self._fence = NEVER
        self.data_loss_events = 0
        self.loss_reason: str | None = None
        self._unverified: str | None = None  # why the open-time check waits for the anchor
        try:
            self._run(self._verify)
        except AnchorUnavailableError as exc:  # start fenced and unready, never refuse to start
            self._unverified = str(exc)
            log.warning("replay state %s: not verified yet (%s); commits wait", self.path, exc)
        self._opened = True
        # Reads (the pre-crypto check, metrics) use their own connections: WAL lets them run
        # beside the writer, so no lookup ever waits behind a group commit's fsyncs, and one
        # connection per concurrent reader lets lookups in several threads run side by side.
        self._readers: queue.SimpleQueue[sqlite3.Connection] = queue.SimpleQueue()
        self._defer = False
        self._outbox: Outbox | None = None
        self._committer: GroupCommitter[_Op, Seen | int] = GroupCommitter(
            self._commit_batch, name=f"antireplay-state:{self.path.name}"
        )

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
                db.executescript(_OUTBOX_SCHEMA)
                return db
            except sqlite3.OperationalError as exc:
                if "locked" not in str(exc) or time.monotonic() > deadline:
                    raise self._unreadable(exc) from None
                time.sleep(0.01)
            except sqlite3.Error as exc:
                raise self._unreadable(exc) from None

    def _unreadable(self, exc: Exception) -> StateFileError:
        return StateFileError(
            str(self.path), f"not a readable replay-state database ({exc})", recovery=self._aside
        )

    @property
    def _aside(self) -> str:
        return _move_aside(self.path)

    def _decode(self, key: str, text: object) -> int:
        return _codec.decode(str(text), where=str(self.path), key=key, recovery=self._aside)

    def _time(self, key: str, value: object) -> float:
        return _codec.decode_float(value, where=str(self.path), key=key, recovery=self._aside)

    def _verify(self) -> None:
        """At open: compare the database with its witness and each anchor copy; fence on any
        sign of loss (and, for a lazy anchor, up to its lease's end, said as a fence)."""

        def body(db: sqlite3.Connection) -> tuple[None, _Meta]:
            meta = db.execute(_META_SELECT).fetchone()
            row = None if meta is None else _decode_meta(meta, self.path, self._aside)
            rows = db.execute("SELECT count(*) FROM seen").fetchone()[0]
            counters = db.execute("SELECT count(*) FROM counters").fetchone()[0]
            found = self.witness.read()
            known = row[0] if row is not None else found[0] if isinstance(found, tuple) else None
            copies = {} if self.anchor is None else self.anchor.read(known)
            reason = _loss_reason(row, found, bool(rows or counters))
            for where, copy in copies.items():
                reason = reason or anchor_reason(row, found, copy, where)
            anchored = [copy for copy in copies.values() if isinstance(copy, Anchored)]
            if row is None:
                deployment = known or (anchored[0].deployment if anchored else uuid.uuid4().hex)
                generation, watermark, fence, losses = 0, _FLOOR, _FLOOR, 0
            else:
                deployment, generation, watermark, fence, losses = row
            if isinstance(found, tuple):
                generation = max(generation, found[1])
                self._wall_hw = max(self._wall_hw, found[2])
            lease = _FLOOR
            for copy in anchored:
                generation = max(generation, copy.generation)
                if self.anchor is not None and self.anchor.lazy:
                    lease = max(lease, copy.time)  # commits since its last write came before
                else:  # the last commit's time
                    self._wall_hw = max(self._wall_hw, copy.time)
            wall = self._clock.wall()
            if reason is None and lease > max(fence, wall):
                reason = (
                    f"restart fence to the lazy state anchor's lease end {lease:.3f}: a copy "
                    "as new as the anchor may lack commits made under that lease"
                )
            if reason is not None:
                fence = max(fence, wall, self._wall_hw, lease)
                losses += 1
                self.loss_reason = reason
                self._lost_pending = self._opened  # found late: the next commit says so
                log.warning("replay state %s: %s; fence raised to %s", self.path, reason, fence)
            self._deployment = deployment
            return None, (generation, watermark, fence, losses)

        self._transaction(body)

    def _verified(self) -> None:
        """Run the open-time check the anchor's absence deferred (each write and readiness
        probe tries again; ``AnchorUnavailableError`` until the anchor answers)."""
        if self._unverified is None:
            return
        pending, self._unverified = self._unverified, None
        try:
            self._verify()
        except BaseException:
            self._unverified = pending
            raise

    def _transaction(
        self, body: Callable[[sqlite3.Connection], tuple[T, _Meta]], *, durable: bool = True
    ) -> T:
        """One write transaction: ``body`` does its work and returns its result and the meta
        it read; the meta row goes out with the next generation, and this process's view
        moves only after COMMIT succeeded.  ``durable``: COMMIT fsyncs the WAL (covering
        every deferred transaction before it), then the witness records the generation now
        durable (never one ahead of it); else ``synchronous=NORMAL``: written to the OS,
        made durable by the next durable commit.  The original error is raised, not the
        ROLLBACK's."""
        self._verified()
        self._same_file()
        db = self._db
        db.execute(f"PRAGMA synchronous={'FULL' if durable else 'NORMAL'}")
        self._begin(db)
        try:
            result, (generation, watermark, fence, losses) = body(db)
            generation += 1
            db.execute(
                "INSERT OR REPLACE INTO meta VALUES (1, ?, ?, ?, ?, ?)",
                (self._deployment, generation, watermark, fence, losses),
            )
            self._wall_hw = max(self._wall_hw, self._clock.wall())
            if self.anchor is not None:
                self.anchor.advance(self._deployment, generation, self._wall_hw)
            db.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):  # SQLite may have rolled back already
                db.execute("ROLLBACK")
            raise
        self._generation = generation
        self._watermark = NEVER if watermark <= _FLOOR else watermark
        self._fence = NEVER if fence <= _FLOOR else fence
        self.data_loss_events = losses
        if durable:
            self._witness(generation)
        return result

    def _begin(self, db: sqlite3.Connection) -> None:
        """``BEGIN IMMEDIATE``, waiting for the write lock up to the busy timeout, but only
        :data:`STALLED_WAIT_S` after a wait that ran out and until a transaction begins
        again: one bounded wait, then every queued operation fails at once (503), not one
        busy timeout each."""
        try:
            db.execute("BEGIN IMMEDIATE")
        except sqlite3.OperationalError as exc:
            if "locked" in str(exc) and not self._stalled:
                self._stalled = True
                db.execute(f"PRAGMA busy_timeout={int(STALLED_WAIT_S * 1000)}")
            raise
        if self._stalled:
            self._stalled = False
            db.execute(f"PRAGMA busy_timeout={int(self._timeout_s * 1000)}")

    def _witness(self, generation: int) -> None:
        """Record a durable generation in the witness; fdatasync it at most every
        :data:`WITNESS_SYNC_S` (always the first time), see the module docstring."""
        now = time.monotonic()
        sync = self._witness_synced is None or now - self._witness_synced >= WITNESS_SYNC_S
        self.witness.write(self._deployment, generation, self._wall_hw, sync=sync)
        if sync:
            self._witness_synced = now

    def _same_file(self) -> None:
        """Refuse to write once the file was deleted or replaced under this process: the
        writer would keep recording into a file nobody can open again (the restart that
        follows fences what it held, from the witness)."""
        if file_identity(self.path) != self._file:
            raise StateUnavailableError(
                f"sqlite {self.path}: the state file was deleted or replaced while running; "
                "restart (the restart fences what the lost file held)"
            )

    def fence(self) -> float:
        return self._fence

    def watermark(self) -> float:
        return self._watermark

    def lookup(self, key: str) -> Seen:
        def query(db: sqlite3.Connection) -> Seen:
            row = db.execute(
                "SELECT (SELECT expires FROM seen WHERE key = ?), watermark, fence FROM meta",
                (key,),
            ).fetchone()
            expiry, watermark, fence = row
            watermark = self._time("meta watermark", watermark)
            fence = self._time("meta fence", fence)
            return Seen(
                NEVER if expiry is None else self._time(f"seen {key!r} expiry", expiry),
                NEVER if watermark <= _FLOOR else watermark,
                NEVER if fence <= _FLOOR else fence,
            )

        if self._unverified is not None:  # no loss check yet: its fence is unknown
            raise StateUnavailableError(f"sqlite {self.path}: not verified ({self._unverified})")
        return _codec.serving(lambda: self._read(query))

    def _read(self, query: Callable[[sqlite3.Connection], T]) -> T:
        """Run ``query`` on an idle reader connection (a new one if all are busy)."""
        try:
            db = self._readers.get_nowait()
        except queue.Empty:
            db = self._run(lambda: self._connect(self._timeout_s))
        try:
            return self._run(lambda: query(db))
        finally:
            self._readers.put(db)

    def _connect(self, timeout_s: float) -> sqlite3.Connection:
        """Another connection to the existing file (``mode=rw``): a deleted file is an error
        (``STATE_UNAVAILABLE``), never a new empty database made behind the writer's back."""
        uri = f"{self.path.resolve().as_uri()}?mode=rw"
        return sqlite3.connect(uri, uri=True, timeout=timeout_s, check_same_thread=False)

    def ready(self) -> None:
        """What a commit needs, recording nothing: the file is still there with its meta row
        and its write lock can be taken within a second (``BEGIN IMMEDIATE``, then
        ``ROLLBACK``), on a connection of its own."""

        def probe() -> None:
            if self.anchor is not None:
                with self._lock:
                    self._verified()  # the deferred open-time check, once the anchor answers
                self.anchor.ping()
            self._same_file()
            db = self._connect(min(self._timeout_s, 1.0))
            try:
                db.execute("BEGIN IMMEDIATE")
                try:
                    row = db.execute(_META_SELECT).fetchone()
                    if row is None:
                        raise sqlite3.DatabaseError("no meta row (replaced or truncated)")
                    _decode_meta(row, self.path, self._aside)
                finally:
                    db.execute("ROLLBACK")
            finally:
                db.close()

        _codec.serving(lambda: self._run(probe))

    def commit(self, key: str, expires_at: float, now: float, force: bool = False) -> Seen:
        """Queue the record for the next group commit; return once it is durable (or,
        deferred by an outbox, written: see :meth:`defer_commits`).  An ESTOP's (``force``)
        waits at most :data:`SAFETY_WAIT_S`, see :func:`_lock_held`."""
        waiter = self._committer.enqueue((key, expires_at, now, force))
        if not force:
            return cast(Seen, waiter.result())
        try:
            return cast(Seen, waiter.result(SAFETY_WAIT_S))
        except TimeoutError:
            raise _lock_held(self.path) from None

    def commit_async(
        self,
        key: str,
        expires_at: float,
        now: float,
        force: bool = False,
        offload: Offload | None = None,
    ) -> asyncio.Future[Seen]:
        """:meth:`commit` from a running event loop: await the batch, holding no thread."""
        waiter = self._committer.enqueue_async((key, expires_at, now, force))
        if not force:
            return cast("asyncio.Future[Seen]", waiter)
        return asyncio.ensure_future(_bounded(cast("asyncio.Future[Seen]", waiter), self.path))

    def outbox(self) -> Outbox:
        """This database's audit outbox (:mod:`antireplay.state.outbox`), made once."""
        if self._outbox is None:
            self._outbox = Outbox(self)
        return self._outbox

    def defer_commits(self) -> None:
        """Commit seen-set entries without an fsync of their own (``synchronous=NORMAL``;
        an ESTOP's still has one): for a caller that follows every accepted commit with a
        durable outbox row, whose fsync makes the entry durable too, before the answer."""
        self._defer = True

    def enqueue_outbox(self, op: Put | Forget | Renew) -> Future[int]:
        """Queue an outbox operation with the next batch (:class:`~.outbox.Outbox`)."""
        return cast("Future[int]", self._committer.enqueue(op))

    def enqueue_outbox_async(self, op: Put) -> asyncio.Future[int]:
        """:meth:`enqueue_outbox` from a running event loop."""
        return cast("asyncio.Future[int]", self._committer.enqueue_async(op))

    def read_outbox(self, query: Callable[[sqlite3.Connection], T]) -> T:
        """``query`` on a reader connection (the outbox's drain and count)."""
        return _codec.serving(lambda: self._read(query))

    def _durable(self, op: _Op) -> bool:
        """Whether ``op`` needs its batch fsynced: an outbox row that asks, a deletion
        never, a seen-set entry unless deferred (an ESTOP's always)."""
        if isinstance(op, tuple):
            return op[3] or not self._defer
        return op.durable

    def _commit_batch(self, ops: Sequence[_Op]) -> list[Seen | int]:
        """One transaction for a batch: bounded purge (raising the watermark), each record
        in order (racers on one key: one winner), outbox rows, meta once, one COMMIT
        (with an fsync if any operation needs one)."""
        records = [op for op in ops if isinstance(op, tuple)]

        def body(db: sqlite3.Connection) -> tuple[list[tuple[float, bool] | int], _Meta]:
            generation, watermark, fence, losses = self._meta_checked(db)
            if records:
                now = min(op[2] for op in records)  # no caller's entry is purged early
                limit = PURGE_BATCH + 2 * len(records)
                purged = db.execute(_PURGE_SELECT, (now, limit)).fetchall()
                if purged:
                    db.executemany("DELETE FROM seen WHERE key = ?", [(k,) for k, _ in purged])
                    watermark = max(watermark, *(e for _, e in purged))
            done = [self._record(db, op) if isinstance(op, tuple) else op.apply(db) for op in ops]
            return done, (generation, watermark, fence, losses)

        def tx() -> list[Seen | int]:
            results = self._transaction(body, durable=any(self._durable(op) for op in ops))
            wm, fence_now, lost = self._watermark, self._fence, self._lost_pending
            self._lost_pending = False
            first = True
            answers: list[Seen | int] = []
            for result in results:
                if isinstance(result, int):
                    answers.append(result)
                    continue
                seen, recorded = result
                answers.append(Seen(seen, wm, fence_now, recorded, False, lost and first))
                first = False
            return answers

        with self._lock:
            answers = _codec.serving(lambda: self._run(tx))
        wake = None if self._outbox is None else self._outbox.on_rows
        if wake is not None and any(isinstance(op, Put) for op in ops):
            wake()
        return answers

    def _meta_checked(self, db: sqlite3.Connection) -> tuple[int, float, float, int]:
        """The meta row, fenced first if the database went back under this process."""
        found = db.execute(_META_SELECT).fetchone()
        row = None if found is None else _decode_meta(found, self.path, self._aside)[1:]
        if row is None or row[0] < self._generation:
            reason = "database rolled back or replaced while running (a live restore?)"
            fence = max(self._clock.wall(), self._wall_hw)
            losses = (row[3] if row is not None else self.data_loss_events) + 1
            log.warning("replay state %s: %s; fence raised to %s", self.path, reason, fence)
            self.loss_reason = reason
            self._lost_pending = True
            generation = max(self._generation, row[0] if row is not None else 0)
            watermark = row[1] if row is not None else _FLOOR
            return generation, watermark, max(fence, row[2] if row is not None else fence), losses
        return row

    def verify(self) -> Seen:
        """Re-read the shared meta row (fence, watermark), checking for a live rollback."""

        def tx() -> Seen:
            self._transaction(lambda db: (None, self._meta_checked(db)))
            return Seen(NEVER, self._watermark, self._fence)

        with self._lock:
            return self._run(tx)

    def _record(self, db: sqlite3.Connection, op: _Record) -> tuple[float, bool]:
        key, expires_at, now, force = op
        found = db.execute("SELECT expires FROM seen WHERE key = ?", (key,)).fetchone()
        seen = NEVER if found is None else self._time(f"seen {key!r} expiry", found[0])
        recorded = not seen >= now
        if recorded or (force and seen < expires_at):
            db.execute("INSERT OR REPLACE INTO seen VALUES (?, ?)", (key, expires_at))
        return seen, recorded

    def advance(self, key: str, value: int) -> bool:
        """Compare-and-advance a counter; like a commit, it moves the generation and witness
        (so a restored copy of the counters is noticed too)."""
        return self.advance_above(key, value, None)

    def advance_above(self, key: str, value: int, fence_key: str | None) -> bool:
        """:meth:`advance`, refused too unless ``value`` is above counter ``fence_key``: one
        transaction."""

        def body(db: sqlite3.Connection) -> tuple[bool, _Meta]:
            meta = self._meta_checked(db)
            row = None if fence_key is None else db.execute(
                "SELECT value FROM counters WHERE key = ?", (fence_key,)
            ).fetchone()  # fmt: skip
            if row is not None and value <= self._decode(str(fence_key), row[0]):
                return False, meta
            return self._advance(db, key, value), meta

        with self._lock:
            return self._run(lambda: self._transaction(body))

    def _advance(self, db: sqlite3.Connection, key: str, value: int) -> bool:
        """Compare-and-advance inside the caller's transaction."""
        if db.execute(_ADVANCE, (key, _codec.encode(value))).rowcount == 1:
            return True
        (held,) = db.execute("SELECT value FROM counters WHERE key = ?", (key,)).fetchone()
        self._decode(key, held)  # refused: by a counter, never by something undecodable
        return False

    def forget(self, keys: Sequence[str], fence_key: str, fence: int) -> None:
        """Raise counter ``fence_key`` to ``fence`` and delete the counters ``keys``, in one
        transaction with :meth:`advance`'s loss detection (the fence itself is kept)."""
        dropped = [(key,) for key in keys if key != fence_key]

        def body(db: sqlite3.Connection) -> tuple[None, _Meta]:
            meta = self._meta_checked(db)
            self._advance(db, fence_key, fence)
            db.executemany("DELETE FROM counters WHERE key = ?", dropped)
            return None, meta

        with self._lock:
            self._run(lambda: self._transaction(body))

    def current(self, key: str) -> int | None:
        row = self._fetch("SELECT value FROM counters WHERE key = ?", (key,))
        return None if row is None else self._decode(key, row[0])

    def count(self) -> int:
        """Rows in the seen-set (live and not yet purged)."""
        row = self._fetch("SELECT count(*) FROM seen", ())
        return 0 if row is None else int(row[0])

    def status(self) -> dict[str, float]:
        return {
            "entries": float(self.count()),
            "watermark": self._watermark,
            "fence": self._fence,
            "evictions": 0.0,
            "data_loss_events": float(self.data_loss_events),
        }

    @property
    def group_commit(self) -> GroupCommitter[Any, Any]:
        """The writer that batches this file's commits (its counters feed /metrics)."""
        return self._committer

    def close(self) -> None:
        self._committer.close()
        while True:
            try:
                self._readers.get_nowait().close()
            except queue.Empty:
                break
        with self._lock:
            self._db.close()
            self.witness.close()
            if self.anchor is not None:
                self.anchor.close()

    def _fetch(self, sql: str, params: tuple[object, ...]) -> tuple[Any, ...] | None:
        def query(db: sqlite3.Connection) -> tuple[Any, ...] | None:
            row: tuple[Any, ...] | None = db.execute(sql, params).fetchone()
            return row

        return self._read(query)

    def _run(self, op: Callable[[], T]) -> T:
        try:
            return op()
        except sqlite3.DatabaseError as exc:
            if "malformed" in str(exc) or "not a database" in str(exc):
                if not self._opened:
                    raise self._unreadable(exc) from None
                raise StateUnavailableError(  # while running: 503, never a traceback
                    f"{self._unreadable(exc)}"
                ) from None
            raise StateUnavailableError(f"sqlite {self.path}: {exc}") from None
        except OSError as exc:
            raise StateUnavailableError(f"sqlite witness {self.witness.path}: {exc}") from None


def _lock_held(path: Path) -> StateUnavailableError:
    """An ESTOP's commit that did not finish within :data:`SAFETY_WAIT_S` (another
    process holds the write lock, or a slow disk): the ESTOP is delivered flagged
    (``estop_survives``); its record stays queued and is committed once the lock frees."""
    return StateUnavailableError(
        f"sqlite {path}: write lock not taken within {SAFETY_WAIT_S}s (another process "
        "holds it?); the ESTOP's record is committed once it frees"
    )


async def _bounded(waiter: asyncio.Future[Seen], path: Path) -> Seen:
    """An ESTOP's commit on an event loop, awaited at most :data:`SAFETY_WAIT_S` (the
    record itself stays queued: ``shield``)."""
    try:
        return await asyncio.wait_for(asyncio.shield(waiter), SAFETY_WAIT_S)
    except TimeoutError:
        raise _lock_held(path) from None


def check_readable(path: str | Path) -> None:
    """Refuse a file that is not a readable database, or whose meta row or expiries do not
    decode, without writing anything (so a ``config check`` never uses up the loss
    detection of the store's next real open)."""
    path = Path(path)
    if not path.exists():
        return
    recovery = _move_aside(path)
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master")}
            if {"meta", "seen"} <= tables:
                _check_rows(db, path, recovery)
        finally:
            db.close()
    except sqlite3.Error as exc:
        raise StateFileError(
            str(path), f"not a readable replay-state database ({exc})", recovery=recovery
        ) from None


def _move_aside(path: Path) -> str:
    """The recovery from a damaged database: the next start fences what it held."""
    return f"mv {path} {path}.corrupt (the next start re-creates it behind a restart fence)"


def _check_rows(db: sqlite3.Connection, path: Path, recovery: str) -> None:
    """Every stored expiry is a number and the meta row decodes (or ``StateFileError``)."""
    bad = db.execute(_SEEN_UNDECODABLE).fetchone()
    if bad is not None:
        key = f"seen {bad[0]!r} expiry"
        raise _codec.undecodable(bad[1], "a number", where=str(path), key=key, recovery=recovery)
    row = db.execute(_META_SELECT).fetchone()
    if row is not None:
        _decode_meta(row, path, recovery)


def _decode_meta(row: tuple[object, ...], path: Path, recovery: str) -> _MetaRow:
    """The meta row's values, each what its column holds (or ``StateFileError``)."""
    deployment, generation, watermark, fence, losses = row
    where = str(path)
    return (
        _codec.decode_hex(deployment, 32, where=where, key="meta deployment", recovery=recovery),
        _codec.decode_int(generation, where=where, key="meta generation", recovery=recovery),
        _codec.decode_float(watermark, where=where, key="meta watermark", recovery=recovery),
        _codec.decode_float(fence, where=where, key="meta fence", recovery=recovery),
        _codec.decode_int(losses, where=where, key="meta data_loss_events", recovery=recovery),
    )


def _loss_reason(  # noqa: PLR0911 - one answer per row of the table in the docstring
    meta: tuple[Any, ...] | None, witness: tuple[str, int, float] | bool | None, has_state: bool
) -> str | None:
    """Why the database may have lost state (None: it provably has not)."""
    if meta is None:
        if witness is None and not has_state:
            return None  # a new deployment
        if witness is None:
            return "state without meta or witness (made by an older version?)"
        return "database missing, truncated or replaced (the witness says it existed)"
    if witness is None:
        return "witness file missing"
    if witness is False:
        return "witness file unreadable"
    assert isinstance(witness, tuple)
    if witness[0] != meta[0]:
        return "database belongs to another deployment than its witness (replaced)"
    if meta[1] < witness[1]:
        return f"database generation {meta[1]} is behind its witness's {witness[1]} (rolled back)"
    return None


def anchor_reason(  # noqa: PLR0911 - one answer per anchor row of the docstring's table
    meta: tuple[Any, ...] | None,
    witness: tuple[str, int, float] | bool | None,
    anchor: Read,
    where: str = "",
) -> str | None:
    """Why a database its witness vouches for may still have lost state, by one copy of
    its anchor (:mod:`antireplay.state.anchor`, at ``where``): what a restored copy of the
    whole directory, or a lost anchor copy, shows."""
    at = f" ({where})" if where else ""
    if anchor is False:
        return f"state anchor{at} unreadable"
    if anchor is None:
        if meta is None and witness is None:
            return None  # a new deployment, anchored from its first commit
        return f"no state anchor{at} for existing state (the anchor was lost, or is new here)"
    if meta is None:
        return (
            f"database and witness missing but the state anchor{at} vouches for generation "
            f"{anchor.generation} (deleted, or restored from before the anchor)"
        )
    if meta[0] != anchor.deployment:
        return f"database belongs to another deployment than its state anchor{at} (replaced)"
    if meta[1] < anchor.generation:
        return (
            f"database generation {meta[1]} is behind its state anchor{at}'s "
            f"{anchor.generation} (the state directory was restored from an older copy)"
        )
    return None
