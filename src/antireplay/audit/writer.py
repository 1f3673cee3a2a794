"""The audit writer: group-committed, hash-chained appends with an anchored head.

See :mod:`antireplay.audit` for the theory of operation, :mod:`.segments` for how the
trail rotates and what retention removes, :mod:`.rotation` for the writer's side of that.
Each batch is one transaction in :meth:`AuditLog._write_batch`; rotation and retention run
after it, under the same lock, and never fail the batch (its rows are durable: a failed
rotation is retried next batch).
Rows waiting in the ESTOP spill (:mod:`.spill`) are merged first in each batch.

With a SQLite state store's outbox (:meth:`AuditLog.attach`, :mod:`antireplay.state.outbox`)
rows are appended there, in the state's own transactions, and each batch here *drains*
it: the rows above the trail's mark (table ``outbox_moved``, carried into each new
segment) are chained and the mark moved in one transaction.  That commit fsyncs only
every ``head_sync_s`` (``synchronous=NORMAL`` otherwise: a ``kill -9`` loses nothing, a
power cut may lose the newest rows, which the outbox still holds and the next drain moves
again, the mark having gone back with them); after an fsynced one the head is
checkpointed and the outbox forgets what the trail now holds durably.  Opening drains
first; closing drains with an fsync.  The head never claims a row not yet durable.  Each
fsynced drain also records the head in the state database (:mod:`.consistency`); a trail
found behind that record when it attaches is ``AUDIT_ROLLED_BACK``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import sqlite3
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from os import PathLike
from pathlib import Path
from typing import Any, NamedTuple

from antireplay.audit import consistency, segments
from antireplay.audit.chain import (
    _FIELDS,
    ROW_FIELDS,
    AuditRow,
    Checkpoint,
    HeadAnchor,
    MacKey,
    Record,
    _compare,
    _digest,
    _last,
    _recovery,
    sanitize,
    spill_key,
    valid_at,
)
from antireplay.audit.rotation import SegmentLifecycle, mark_of, rows_in
from antireplay.audit.segments import Retention
from antireplay.audit.spill import SLOTS, Spill
from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import AuditFileError, StateUnavailableError
from antireplay.state.durable import file_identity
from antireplay.state.groupcommit import GroupCommitter
from antireplay.state.outbox import Mark, Outbox

log = logging.getLogger("antireplay.audit")
#: A queued "move what the outbox holds" (no row of its own).
_DRAIN = None
#: Outbox rows moved per transaction at most (more: another drain follows at once).
DRAIN_BATCH = 4096


class _Appended(NamedTuple):
    """What one batch's transaction wrote: rows moved from the outbox, the outbox mark, the
    sequence number of the first row given directly, and the new head (rows, hash) with
    the time of its first row."""

    moved: int
    mark: Mark
    first: int
    rows: int
    head: str
    first_at: object


def _stored(row: AuditRow) -> dict[str, Any]:
    """One row as stored and hashed (the outbox and the spill keep it as JSON):
    identifiers sanitized, the flag an integer."""
    stored = {name: getattr(row, name) for name in ROW_FIELDS}
    stored["sender"], stored["msg_id"] = sanitize(row.sender), sanitize(row.msg_id)
    stored["sender_verified"] = int(row.sender_verified)
    return stored


def stored_json(row: AuditRow) -> str:
    """One row as the outbox keeps it (JSON text of :func:`_stored`)."""
    return json.dumps(_stored(row))


class AuditLog(SegmentLifecycle):
    """Append-only, hash-chained audit trail: the live segment at ``path`` and the rotated
    segments beside it (:mod:`.segments`), head anchored outside them."""

    def __init__(
        self,
        path: str | PathLike[str],
        *,
        head_key: str | Path | MacKey | None = None,
        head_path: str | Path | None = None,
        head_sync_s: float = 1.0,
        clock: Clock | None = None,
        retention: Retention | None = None,
        spill_path: str | Path | None = None,
        spill_slots: int = SLOTS,
    ) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.anchor = HeadAnchor(self.path, head_key,
                                 Path(head_path) if head_path else None)  # fmt: skip
        #: Longest a checkpoint stays un-fsynced while rows are appended (power cuts only).
        self.head_sync_s = head_sync_s
        #: When the live segment rotates and what is removed (default: one growing file).
        self.retention = retention or Retention()
        self._clock = resolve(clock)
        self._head_synced = self._clock.monotonic()
        self._head_dirty = False
        self._refuse_deleted_trail()
        db = self._open_lifecycle()  # the rotation lock held shared until _opened
        self._lock = threading.Lock()
        try:
            self._key = self._open_anchor(db)
            self._rows, self._head = _last(db)  # what this writer knows the chain to be
            self._opened(db)
        except BaseException as exc:
            self._close_live()
            self._rotation.close()
            if isinstance(exc, sqlite3.DatabaseError):
                raise AuditFileError(
                    str(self.path),
                    f"not a usable audit segment ({exc})",
                    recovery=_recovery(self.path),
                ) from None
            raise
        self._live_since = self._first_at(self._live())
        self._outbox: Outbox | None = None
        self._drain_queued = False
        self._forgotten: Mark = (None, 0)
        self._recorded: tuple[int, str] | None = None
        #: Record the head in the state database with each drain (off: to measure its cost).
        self.record_head = True
        #: Why the trail was found rolled back against the state's record (``None``: it was
        #: not), and how often; the flag holds until the process stops.
        self.rolled_back: str | None = None
        self.rollbacks = 0
        #: Why the last head checkpoint could not be written (a head key in a token that
        #: failed, the head file): the rows are in the trail but its head lags them
        #: (``None``: written).  ``head_failures`` counts failed checkpoints.
        self.head_behind: str | None = None
        self.head_failures = 0
        self._last_moved = 0
        #: The connection whose ``synchronous`` was last set, and to FULL (True) or not.
        self._synchronous: tuple[sqlite3.Connection | None, bool] = (None, True)
        self._spill = self._open_spill(spill_path, spill_slots)
        self._committer: GroupCommitter[AuditRow | None, int] = GroupCommitter(
            self._write_batch, name=f"antireplay-audit:{self.path.name}"
        )

    # --- the ESTOP spill (audit/spill.py): reserved at open, merged with each batch -------------

    def _open_spill(self, path: str | Path | None, slots: int) -> Spill | None:
        """Reserve the spill and merge what a previous run left in it; without one (no
        slots, or no space to reserve it) held rows stay in the caller's memory."""
        if slots <= 0:
            return None
        where = Path(path) if path else self.path.with_name(self.path.name + ".spill")
        try:
            spill = Spill(where, spill_key(self._key), slots=slots)
        except AuditFileError as exc:
            log.error("audit spill unavailable (%s): ESTOP rows are held in memory", exc)
            return None
        self._spill = spill
        waiting = len(spill.pending())
        if waiting:
            try:
                self._write_batch([])
                log.warning("merged %d spilled audit rows into %s", waiting, self.path)
            except (sqlite3.Error, OSError, AuditFileError) as exc:
                log.error("spilled audit rows not merged yet (%s): next batch", exc)
        return spill

    def spill(self, row: AuditRow) -> bool:
        """Keep one row that the trail could not take in the reserved spill, durably; it is
        merged, chained, with the next batch the trail commits.  ``False``: no room."""
        return self._spill is not None and self._spill.add(_stored(row))

    @property
    def spilled(self) -> int:
        """Rows waiting in the spill."""
        return 0 if self._spill is None else len(self._spill.pending())

    def pairs_with(self, store: object) -> bool:
        """Whether an accepted command's row may ride in ``store``'s commit of its entry
        (:class:`~antireplay.state.outbox.Paired`): this trail takes its rows through that
        store's outbox (whose writer puts no paired row once the live segment is gone: the
        row is then queued apart, and fails: :meth:`append_later`)."""
        outbox = self._outbox
        return outbox is not None and outbox.store is store

    def append(self, row: AuditRow) -> int:
        """Durably append one record; returns its sequence number.

        Raises ``STATE_UNAVAILABLE`` when the record cannot be made durable (disk full,
        closed database): callers must not act on a message they could not audit.
        """
        try:
            future = self.append_later(row, durable=True)
            assert isinstance(future, Future)
            return future.result()
        except (sqlite3.Error, OSError, RuntimeError, AuditFileError) as exc:
            raise StateUnavailableError(f"audit trail unavailable: {exc}") from None

    def append_later(
        self,
        row: AuditRow,
        *,
        on_loop: bool = False,
        durable: bool | None = None,
    ) -> Future[int] | asyncio.Future[int]:
        """Queue one record for the next group commit; the future completes once it is
        durable (``on_loop``: an asyncio future of the running loop, which awaits it before
        answering, holding no thread).  With an outbox, a refusal's (``durable`` defaults
        to ``outcome == "accepted"``) completes once written where a ``kill -9`` cannot
        lose it, durable with the next fsynced batch."""
        if self._outbox is not None:
            sync = row.outcome == "accepted" if durable is None else durable
            if not self._there():  # the row would wait for a lost trail
                return _failed(self._gone(), on_loop=on_loop)
            if on_loop:
                return self._outbox.put_async(_stored(row), durable=sync)
            return self._outbox.put(_stored(row), durable=sync)
        if on_loop:
            return self._committer.enqueue_async(row)
        return self._committer.enqueue(row)

    def _write_batch(self, batch: Sequence[AuditRow | None], *, sync: bool = False) -> list[int]:
        """Chain and commit a group of rows (spilled ones first, then the outbox's) in one
        write transaction; one head checkpoint; then rotate and retain if due (never
        failing the batch: its rows are written).  Each queued drain answers ``0``."""
        with self._lock:
            self._drain_queued = False  # a row put from now on wakes another drain
            spilled = [] if self._spill is None else self._spill.pending()  # merged first
            direct = [row for row in batch if row is not _DRAIN]
            outbox = self._outbox
            sync = sync or outbox is None or bool(spilled or direct)
            sync = sync or self._clock.monotonic() - self._head_synced >= self.head_sync_s
            with self._shared() as db:  # no rotation meanwhile
                if self._synchronous != (db, sync):  # a statement only when it changes
                    db.execute(f"PRAGMA synchronous={'FULL' if sync else 'NORMAL'}")
                    self._synchronous = (db, sync)
                db.execute("BEGIN IMMEDIATE")
                try:
                    done = self._append(db, spilled, direct)
                    db.execute("COMMIT")
                except BaseException:
                    with contextlib.suppress(sqlite3.Error):  # a full disk: SQLite rolled back
                        db.execute("ROLLBACK")
                    raise
                self._rows, self._head = done.rows, done.head
                if self._live_since is None and done.first_at is not None:
                    self._live_since = valid_at(done.first_at)
                if outbox is None:  # the head under the lock: never a retention's stale mark
                    self._head_written(self._checkpoint)
                elif sync:  # the head claims only rows made durable; so does the outbox's delete
                    self._head_written(lambda: self._checkpoint(sync=True, forget=done.mark))
                else:
                    self._head_dirty = True
            if spilled:
                self._merged(len(spilled))
            self._after_batch()
            self._last_moved = done.moved
            if done.moved == DRAIN_BATCH:
                self._wake()  # more waiting: drain on
            seqs = iter(range(done.first, done.rows + 1))
            return [0 if row is _DRAIN else next(seqs) for row in batch]

    def _append(
        self, db: sqlite3.Connection, spilled: list[dict[str, Any]], direct: list[AuditRow]
    ) -> _Appended:
        """Inside the batch's transaction: check the file is still this writer's, chain the
        spilled rows, the outbox's above the mark (moving the mark) and ``direct``."""
        # Rows deleted or rewritten under a running writer must not be adopted by its next
        # checkpoint: the chain must still hold what this writer wrote (another writer may
        # have extended it).
        problem = _compare(db, Checkpoint(self._rows, self._head))
        if problem is not None:
            log.error("audit trail %s %s; refusing to append", self.path, problem)
            raise AuditFileError(str(self.path), problem, recovery=_recovery(self.path))
        moved: list[tuple[int, dict[str, Any]]] = []
        mark: Mark = (None, 0)
        if self._outbox is not None:
            mark = mark_of(db)
            epoch, moved = self._outbox.pending(mark, DRAIN_BATCH)
            mark = (epoch, mark[1] if mark[0] == epoch else 0)
        seq, prev = _last(db)
        # Each row as stored, in a dict of its own (the outbox's are fresh from JSON) that
        # takes its seq: the hash covers it, the columns are read from it.
        rows = [*map(dict, spilled), *(fields for _, fields in moved), *map(_stored, direct)]
        first, values = seq + 1 + len(spilled) + len(moved), []
        for row in rows:
            seq += 1
            row["seq"] = seq
            digest = _digest(prev, row)
            values.append((*(row[f] for f in _FIELDS), prev, digest))
            prev = digest
        db.executemany("INSERT INTO audit VALUES (?,?,?,?,?,?,?,?,?,?,?)", values)
        if moved:
            mark = (mark[0], moved[-1][0])
            db.execute("INSERT OR REPLACE INTO outbox_moved VALUES (1, ?, ?)", mark)
        return _Appended(len(moved), mark, first, seq, prev, rows[0]["at"] if rows else None)

    def attach(self, outbox: Outbox) -> None:
        """Take audit rows through ``outbox`` from now on (its store defers its commits to
        the accepted rows that follow them); what it already holds is drained first."""
        with self._lock, self._shared() as db:
            db.execute(segments.MARK_SCHEMA)
            found = consistency.against_state(self.path, db, outbox.trail_head(), self._key)
        if found is not None and found.problem is not None:
            self._roll_back(f"behind the state database {outbox.store.path}: {found.problem}")
        self._outbox = outbox
        outbox.trail_there = self._there
        outbox.store.defer_commits()
        self.drain()
        outbox.on_rows = self._wake

    def _there(self) -> bool:
        """Whether the live segment is still there (not deleted under this writer); a path
        that cannot be stat'ed (EIO, EACCES, ENOTDIR) is not there either: fail closed,
        typed, never a raw ``OSError`` on the loop or in the state writer's batch."""
        try:
            return file_identity(self.path) is not None
        except OSError:
            return False

    def _roll_back(self, problem: str) -> None:
        """The trail disagrees with the state's record of its head: say so (log, flag,
        counter) and put it on the record, an ``AUDIT_ROLLED_BACK`` row chained now."""
        self.rolled_back, self.rollbacks = problem, self.rollbacks + 1
        log.error("audit trail %s rolled back: %s", self.path, problem)
        row = AuditRow(self._clock.wall(), "alert", consistency.ROLLED_BACK, problem[:200])
        self._write_batch([row], sync=True)

    def drain(self) -> None:
        """Move everything the outbox holds into the trail now, durably (a database behind
        the trail's mark gets a new epoch first: see :mod:`antireplay.state.outbox`)."""
        if self._outbox is None:
            return
        with self._lock, self._shared() as db:
            mark = mark_of(db)
        if self._outbox.behind(mark):
            self._roll_back(f"the state database {self._outbox.store.path} is behind the "
                            "trail (its outbox never reached the trail's mark): restored "
                            "from an older copy; its outbox starts a new epoch")  # fmt: skip
            self._outbox.renew().result()
        while True:
            self._write_batch([_DRAIN], sync=True)
            if self._last_moved < DRAIN_BATCH:
                return

    def _wake(self) -> None:
        """Rows were put in the outbox: queue one drain (called on the store's writer)."""
        if self._drain_queued:
            return
        self._drain_queued = True
        with contextlib.suppress(RuntimeError):  # closing: the close drains
            self._committer.enqueue(_DRAIN)

    def _forget(self, outbox: Outbox, mark: Mark) -> None:
        """The trail holds rows up to ``mark`` durably: delete them from the outbox (of
        that epoch: the delete names it)."""
        head = (self._rows, self._head)
        if (mark == self._forgotten or mark[1] == 0) and (
            not self.record_head or head == self._recorded or not self._rows
        ):
            return
        self._forgotten = mark
        record = None
        if self.record_head:  # the head, durable now: kept in the state database too
            self._recorded = head
            mac = HeadAnchor.mac(self._key, self._rows, self._head, self._first)
            record = (self._rows, self._head, self._first, mac)
        self._forget_point()
        with contextlib.suppress(RuntimeError):  # the store is closing: deleted next time
            outbox.forget(mark, record)

    def _forget_point(self) -> None:
        """Called between a durable drain and the outbox's delete (a test stops there)."""

    def _merged(self, n: int) -> None:
        """Spilled rows are durable in the trail: clear them from the spill."""
        assert self._spill is not None
        try:
            self._spill.merged(n)
        except OSError as exc:  # merged again later: a duplicate row, never a lost one
            log.error("audit spill %s not cleared after its merge: %s", self._spill.path, exc)
        else:
            log.warning("audit trail writable again: %d spilled rows merged", n)

    def _head_written(self, checkpoint: Callable[[], None]) -> None:
        """Run ``checkpoint``; a head that cannot be written is said at once (logged when
        it starts and ends, :attr:`head_behind` for the metric and readiness), never only
        at close: the batch still fails, so the outbox keeps the rows it moved."""
        try:
            checkpoint()
        except (OSError, sqlite3.Error, AuditFileError) as exc:
            self.head_failures += 1
            if self.head_behind is None:
                log.error(
                    "audit head %s cannot be written (%s): rows still reach the trail but its "
                    "head checkpoint lags them and the state's outbox keeps them; AUDIT_HEAD_"
                    "BEHIND until a checkpoint is written", self.anchor.path, exc,
                )  # fmt: skip
            self.head_behind = str(exc)[:200] or type(exc).__name__
            raise
        if self.head_behind is not None:
            log.warning("audit head %s written again", self.anchor.path)
            self.head_behind = None

    def _checkpoint(self, *, sync: bool = False, forget: Mark | None = None) -> None:
        """Rewrite the head after a batch (the caller holds the lock); fsync it only once
        ``head_sync_s`` has passed since the last fsync (see the module docstring); then,
        given the drained ``forget`` mark, the outbox forgets what the trail holds."""
        now = self._clock.monotonic()
        sync = sync or now - self._head_synced >= self.head_sync_s
        self.anchor.write(self._key, self._rows, self._head, sync=sync, first=self._first)
        if sync:
            self._head_synced = now
        self._head_dirty = not sync
        if forget is not None and self._outbox is not None:
            self._forget(self._outbox, forget)

    def tail(self, n: int = 20) -> list[Record]:
        """The newest ``n`` records across segments (read-only connections), the outbox's
        rows moved first."""
        self._moved_now()
        return segments.newest(self.path, n)

    def _moved_now(self) -> None:
        """Queue a drain and wait for it (rows put so far are in the trail after it)."""
        if self._outbox is not None:
            with contextlib.suppress(RuntimeError, sqlite3.Error, OSError, AuditFileError,
                                     StateUnavailableError):  # fmt: skip
                self._committer.submit(_DRAIN)

    def count(self) -> int:
        """Records kept across segments."""
        self._moved_now()
        with self._lock, self._shared() as db:
            live = int(db.execute("SELECT count(*) FROM audit").fetchone()[0])
            return live + sum(rows_in(k.path) for k in self._kept)

    @property
    def group_commit(self) -> GroupCommitter[Any, Any]:
        """The writer that batches this file's commits (its counters feed /metrics)."""
        return self._committer

    def close(self) -> None:
        """Write what is queued (and what is spilled, if the trail takes it now), make the
        head durable, then close."""
        self._committer.close()
        if self._outbox is not None:  # rows still queued in the store's writer: in first
            with contextlib.suppress(RuntimeError, StateUnavailableError):
                self._outbox.flush()
        if self.spilled or self._outbox is not None:
            with contextlib.suppress(sqlite3.Error, OSError, AuditFileError, StateUnavailableError):
                self._write_batch([], sync=True)  # else merged (or drained) at the next start
        with self._lock:
            try:
                if self._head_dirty:
                    with self._shared():
                        self.anchor.write(self._key, self._rows, self._head, sync=True,
                                          first=self._first)  # fmt: skip
                    self._head_dirty = False
            except (OSError, sqlite3.Error, AuditFileError) as exc:  # the head lags: under-claims
                log.warning("audit head %s not made durable at close: %s", self.anchor.path, exc)
            finally:
                self._close_live()
                self._rotation.close()
                if self._spill is not None:
                    self._spill.close()


def _failed(error: BaseException, *, on_loop: bool) -> Future[int] | asyncio.Future[int]:
    """A queued row's future that has already failed with ``error``."""
    future: Future[int] | asyncio.Future[int]
    future = asyncio.get_running_loop().create_future() if on_loop else Future()
    future.set_exception(error)
    return future
