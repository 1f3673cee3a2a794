"""SqliteStore: replay state on one machine that survives kill -9 and reboots, and notices loss.

Size: one idea, one connection: the open-time check, the witness, the group commit and
readiness share one SQLite connection and one lock (the loss decision itself is pure, in
:mod:`.loss`; the read-only checks in :mod:`.sqlite_check`).

Theory of operation
-------------------
WAL with ``synchronous=FULL``: a ``commit`` returns once its transaction is durable.
Commits are **group-committed** (:mod:`.groupcommit`): one transaction and one fsync per
batch; with an audit outbox (:mod:`.outbox`) the batch carries audit rows too: an accepted
command's entry and row as one operation (:meth:`SqliteStore.commit_with_row_async`), and
other entries *deferred* (``synchronous=NORMAL``) to the accepted row whose fsync covers both.
Processes may share one file (``BEGIN IMMEDIATE``).  A fresh ESTOP waits for the write
lock at most :data:`SAFETY_WAIT_S`, then is delivered flagged ``STATE_UNAVAILABLE`` while
its record stays queued; after one busy timeout ran out, operations fail after
:data:`STALLED_WAIT_S` until a transaction begins again.

* **Entries live to their own expiry**: each commit purges at most ``PURGE_BATCH``
  expired rows and raises the persisted watermark to the largest expiry removed, in the
  same transaction (a clock step forward and back re-opens nothing).
* **Continuity is proven or fenced.**  A hidden **witness** file (``.state.db.witness``,
  so ``rm state.db*`` leaves it) holds the deployment id, the durable generation and the
  highest commit time; it is rewritten after each durable COMMIT (never ahead of the
  database) and fdatasync-ed at most every :data:`WITNESS_SYNC_S`.  A witness failure
  after a COMMIT is not a failed commit: the data is durable; it is logged once, counted
  (``witness_failures``) and readiness says so until a witness write succeeds again.  At
  open :func:`.loss.decide` compares the meta row, the witness and each anchor copy
  (:mod:`.anchor`); anything unproven, a state with **no history** included, raises the
  fence to the wall time (persisted in ``meta``; the window refuses what is stamped at or
  before ``fence + skew``).  While running, a database whose generation went back is a
  live restore: fenced too.  A file deleted, replaced or undecodable while running
  answers ``STATE_UNAVAILABLE`` (a fresh ESTOP still passes) and names the recovery.
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
from antireplay.state import _codec, loss
from antireplay.state.anchor import AnchorUnavailableError, StateAnchor
from antireplay.state.contract import Offload
from antireplay.state.durable import Witness, file_identity
from antireplay.state.groupcommit import GroupCommitter
from antireplay.state.outbox import SCHEMA as _OUTBOX_SCHEMA
from antireplay.state.outbox import Forget, Outbox, Paired, Put, Renew
from antireplay.state.sqlite_check import META_SELECT as _META_SELECT
from antireplay.state.sqlite_check import check_readable, decode_meta, move_aside

#: ``check_readable`` stays importable from here (it moved to :mod:`.sqlite_check`).
__all__ = ["SAFETY_WAIT_S", "STALLED_WAIT_S", "WITNESS_SYNC_S", "SqliteStore", "check_readable"]
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
#: One queued seen-set commit: key, expires_at, now, force.
_Record = tuple[str, float, float, bool]
#: What the writer takes: a seen-set commit, one paired with its row, or an outbox row (or
#: its deletion).
_Op = _Record | Paired | Put | Forget | Renew
#: What a paired commit answers: what the commit found (or why its row failed, typed), and
#: the id of the row it put (0: none).
PairedResult = tuple[Seen | StateUnavailableError, int]
#: How long a fresh ESTOP's commit waits for the write lock before it is delivered anyway.
SAFETY_WAIT_S: Final = 0.2
#: How long a transaction waits for the write lock after a wait ran out (see ``_begin``).
STALLED_WAIT_S: Final = 0.05
#: How long the witness may go without an fdatasync while commits move it (see docstring).
WITNESS_SYNC_S: Final = 1.0
#: The meta row as a transaction read it: generation, watermark, fence, data-loss events.
_Meta = tuple[int, float, float, int]
_FLOOR = loss.FLOOR
_HOLDS_STATE = "SELECT EXISTS (SELECT 1 FROM seen) OR EXISTS (SELECT 1 FROM counters)"


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
        self._synchronous = True  # the writer connection's synchronous=FULL (else NORMAL)
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
        self.no_history = False  # this state had no history at open (fenced as such)
        self.witness_failures = 0
        self._witness_error: str | None = None  # the last witness write failed: why
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
        self._committer: GroupCommitter[_Op, Seen | int | PairedResult] = GroupCommitter(
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
        return move_aside(self.path)

    def _decode(self, key: str, text: object) -> int:
        return _codec.decode(str(text), where=str(self.path), key=key, recovery=self._aside)

    def _time(self, key: str, value: object) -> float:
        return _codec.decode_float(value, where=str(self.path), key=key, recovery=self._aside)

    def _verify(self) -> None:
        """At open: compare the database with its witness and each anchor copy; fence on any
        sign of loss (and, for a lazy anchor, up to its lease's end, said as a fence)."""

        def body(db: sqlite3.Connection) -> tuple[None, _Meta]:
            meta = db.execute(_META_SELECT).fetchone()
            row = None if meta is None else decode_meta(meta, self.path, self._aside)
            held = db.execute(_HOLDS_STATE).fetchone()[0]
            found = self.witness.read()
            copies = (
                {} if self.anchor is None else self.anchor.read(loss.known_deployment(row, found))
            )
            lazy = self.anchor is not None and self.anchor.lazy
            d = loss.decide(
                row, found, bool(held), copies, lazy=lazy, wall=self._clock.wall(),
                wall_hw=self._wall_hw, new_id=uuid.uuid4().hex,
            )  # fmt: skip
            self._wall_hw, self._deployment = d.wall_hw, d.deployment
            if d.reason is not None:
                self.loss_reason, self.no_history = d.reason, d.no_history
                self._lost_pending = self._opened  # found late: the next commit says so
                log.warning("replay state %s: %s; fence raised to %s", self.path, d.reason, d.fence)
            return None, (d.generation, d.watermark, d.fence, d.losses)

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
        if durable is not self._synchronous:  # set only when it changes (a statement each)
            db.execute(f"PRAGMA synchronous={'FULL' if durable else 'NORMAL'}")
            self._synchronous = durable
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
        :data:`WITNESS_SYNC_S` (always the first time), see the module docstring.  The
        COMMIT before it is durable whatever happens here: a failure is logged once,
        counted and shown by readiness, never raised as a failed commit (a witness left
        behind only under-claims)."""
        now = time.monotonic()
        sync = self._witness_synced is None or now - self._witness_synced >= WITNESS_SYNC_S
        try:
            self.witness.write(self._deployment, generation, self._wall_hw, sync=sync)
        except OSError as exc:
            self.witness_failures += 1
            if self._witness_error is None:
                log.error(
                    "replay state %s: witness %s not written (%s); commits stay durable, "
                    "the next start's loss check is weaker until it is",
                    self.path, self.witness.path, exc,
                )  # fmt: skip
            self._witness_error = f"witness {self.witness.path} not written: {exc}"
            self._witness_synced = None  # the next write syncs
            return
        if self._witness_error is not None:
            log.warning("replay state %s: witness %s written again", self.path, self.witness.path)
            self._witness_error = None
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
            if self._witness_error is not None:  # commits go through; the check is weaker
                with self._lock:
                    self._witness(self._generation)  # tried again: ready once it is written
                if self._witness_error is not None:
                    raise StateUnavailableError(f"sqlite {self.path}: {self._witness_error}")
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
                    decode_meta(row, self.path, self._aside)
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

    def commit_with_row(
        self, key: str, expires_at: float, now: float, row: Callable[[Seen], str | None]
    ) -> PairedResult:
        """:meth:`commit_with_row_async` for a thread: block until the batch is durable."""
        waiter = self._committer.enqueue(Paired((key, expires_at, now, False), row))
        return cast(PairedResult, waiter.result())

    def commit_with_row_async(
        self, key: str, expires_at: float, now: float, row: Callable[[Seen], str | None]
    ) -> asyncio.Future[PairedResult]:
        """A seen-set commit and its audit row in ONE operation of the next batch, from a
        running event loop (:class:`~.outbox.Paired`): what the commit found and the id of
        the row put in the outbox in the same transaction (0: ``row`` gave none).  Not for
        an ESTOP's (its bounded wait and spill need the two apart: :meth:`commit_async`)."""
        waiter = self._committer.enqueue_async(Paired((key, expires_at, now, False), row))
        return cast("asyncio.Future[PairedResult]", waiter)

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

    def _commit_batch(self, ops: Sequence[_Op]) -> list[Seen | int | PairedResult]:
        """One transaction for a batch: bounded purge (raising the watermark), each record
        in order (racers on one key: one winner), a paired record's row right after it,
        outbox rows, meta once, one COMMIT (with an fsync if any operation needs one)."""
        records = [op.record if isinstance(op, Paired) else op for op in ops
                   if isinstance(op, (tuple, Paired))]  # fmt: skip
        # Paired rows only into an outbox whose trail is still there: once per batch, on
        # this thread (a stat on the loop waits for the GIL after it), before BEGIN (never
        # holding the write lock); a check that fails is "not there", never the batch's.
        rows = not any(isinstance(op, Paired) for op in ops) or self._trail_there()
        lost = False  # a loss still unheard after the batch (by body)

        def body(db: sqlite3.Connection) -> tuple[list[Seen | int | PairedResult], _Meta]:
            generation, watermark, fence, losses = self._meta_checked(db)
            if records:
                now = min(op[2] for op in records)  # no caller's entry is purged early
                limit = PURGE_BATCH + 2 * len(records)
                purged = db.execute(_PURGE_SELECT, (now, limit)).fetchall()
                if purged:
                    db.executemany("DELETE FROM seen WHERE key = ?", [(k,) for k, _ in purged])
                    watermark = max(watermark, *(e for _, e in purged))
            # What the callers are answered: the watermark and fence this transaction commits.
            wm = NEVER if watermark <= _FLOOR else watermark
            fenced = NEVER if fence <= _FLOOR else fence
            nonlocal lost
            lost = self._lost_pending  # said to the first record answered a Seen
            done: list[Seen | int | PairedResult] = []
            for op in ops:
                if isinstance(op, (Put, Forget, Renew)):
                    done.append(op.apply(db))
                    continue
                paired = op if isinstance(op, Paired) else None
                expiry, recorded = self._record(db, op.record if isinstance(op, Paired) else op)
                seen = Seen(expiry, wm, fenced, recorded, False, lost)
                answer: Seen | PairedResult = seen
                if paired is not None:  # not put: its row is queued apart, which fails
                    answer = _paired(db, paired, seen) if rows else (seen, 0)
                heard = isinstance(answer, Seen) or isinstance(answer[0], Seen)
                lost = lost and not heard
                done.append(answer)
            return done, (generation, watermark, fence, losses)

        def tx() -> list[Seen | int | PairedResult]:
            answers = self._transaction(body, durable=any(self._durable(op) for op in ops))
            self._lost_pending = lost  # a loss no record heard (outbox ops only) waits
            return answers

        with self._lock:
            answers = _codec.serving(lambda: self._run(tx))
        wake = None if self._outbox is None else self._outbox.on_rows
        if wake is not None and any(isinstance(op, (Put, Paired)) for op in ops):
            wake()
        return answers

    def _trail_there(self) -> bool:
        """Whether the outbox's trail is still there (``True`` with no trail attached); a
        check that raises counts as not there (logged)."""
        there = self._outbox.trail_there if self._outbox is not None else None
        try:
            return there is None or there()
        except Exception as exc:
            log.error("audit trail check failed (paired rows not put): %r", exc)
            return False

    def _meta_checked(self, db: sqlite3.Connection) -> tuple[int, float, float, int]:
        """The meta row, fenced first if the database went back under this process."""
        found = db.execute(_META_SELECT).fetchone()
        row = None if found is None else decode_meta(found, self.path, self._aside)[1:]
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
        """One seen-set record inside the batch's transaction: the expiry held before it,
        and whether it wrote the entry."""
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
            "no_history_events": float(self.no_history),
            "witness_failures": float(self.witness_failures),
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


def _paired(db: sqlite3.Connection, paired: Paired, seen: Seen) -> PairedResult:
    """A paired record's row into the outbox (its id), or none (0).  A ``row`` that raises
    fails its own operation only, typed (its batch-mates, ESTOPs included, commit)."""
    try:
        row = paired.row(seen)
    except Exception as exc:
        log.error("audit row of %r not built: %r", paired.record[0], exc)
        return StateUnavailableError(f"audit row of {paired.record[0]!r} not built: {exc!r}"), 0
    return seen, 0 if row is None else Put(row, True).apply(db)


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
