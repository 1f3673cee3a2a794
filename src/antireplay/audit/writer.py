"""The audit writer: group-committed, hash-chained appends with an anchored head.

See :mod:`antireplay.audit` for the theory of operation and :mod:`.segments` for how
the trail rotates and what retention removes.  Each batch is one transaction in
:meth:`AuditLog._write_batch`; rotation and retention run after it, under the same lock,
and never fail the batch (its rows are durable: a failed rotation is retried next batch).
Rows waiting in the ESTOP spill (:mod:`.spill`) are merged first in each batch.

With a SQLite state store's outbox (:meth:`AuditLog.attach`, :mod:`antireplay.state.outbox`)
rows are appended there, in the state's own transactions, and each batch here *drains*
it: the rows above the trail's mark (table ``outbox_moved``, carried into each new
segment) are chained and the mark moved in one transaction.  That commit fsyncs only
every ``head_sync_s`` (``synchronous=NORMAL`` otherwise: a ``kill -9`` loses nothing, a
power cut may lose the newest rows, which the outbox still holds and the next drain moves
again, the mark having gone back with them); after an fsynced one the head is
checkpointed and the outbox forgets what the trail now holds durably.  Opening drains
first; closing drains with an fsync.  The head never claims a row not yet durable.

Size: the writer, the spill merge, the outbox drain, rotation and retention share one
lock and one batch.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sqlite3
import threading
from collections.abc import Iterator, Sequence
from concurrent.futures import Future
from os import PathLike
from pathlib import Path
from typing import Any, NamedTuple

from antireplay.audit import consistency, segments
from antireplay.audit.chain import (
    _FIELDS,
    Checkpoint,
    HeadAnchor,
    Record,
    _compare,
    _connect,
    _digest,
    _last,
    _link,
    _recovery,
    sanitize,
    valid_at,
)
from antireplay.audit.segments import Kept, Retention, TrailUsage
from antireplay.audit.spill import SLOTS, Spill
from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import AuditFileError, StateUnavailableError
from antireplay.state.durable import file_identity
from antireplay.state.groupcommit import GroupCommitter
from antireplay.state.outbox import Mark, Outbox

log = logging.getLogger("antireplay.audit")
#: A queued "move what the outbox holds" (no row of its own).
_DRAIN: dict[str, Any] = {}
#: Outbox rows moved per transaction at most (more: another drain follows at once).
DRAIN_BATCH = 4096
#: Longest a due rotation waits for other writers' batches in flight (then postponed).
ROTATION_WAIT_S = 0.5


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


def _stored(fields: dict[str, Any]) -> dict[str, Any]:
    """One row as stored: identifiers sanitized, the flag an integer."""
    return {
        **fields, "sender": sanitize(fields["sender"]),
        "sender_verified": int(fields["sender_verified"]), "msg_id": sanitize(fields["msg_id"]),
    }  # fmt: skip


class AuditLog:
    """Append-only, hash-chained audit trail: the live segment at ``path`` and the rotated
    segments beside it (:mod:`.segments`), head anchored outside them."""

    def __init__(
        self,
        path: str | PathLike[str],
        *,
        head_key: str | Path | None = None,
        head_path: str | Path | None = None,
        head_sync_s: float = 1.0,
        clock: Clock | None = None,
        retention: Retention | None = None,
        spill_path: str | Path | None = None,
        spill_slots: int = SLOTS,
    ) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.anchor = HeadAnchor(self.path, Path(head_key) if head_key else None,
                                 Path(head_path) if head_path else None)  # fmt: skip
        #: Longest a checkpoint stays un-fsynced while rows are appended (power cuts only).
        self.head_sync_s = head_sync_s
        #: When the live segment rotates and what is removed (default: one growing file).
        self.retention = retention or Retention()
        self._rotates = self.retention.segment_bytes is not None or (
            self.retention.segment_age_s is not None
        )
        self._clock = resolve(clock)
        self._head_synced = self._clock.monotonic()
        self._head_dirty = False
        #: Rotations that were due but had to wait (another writer or reader had the trail).
        self.rotations_postponed = 0
        self._waiting = False
        self._refuse_deleted_trail()
        self._rotation = segments.RotationLock(self.path)  # shared: no writer is rotating now
        try:
            segments.recover(self.path)  # a rotation killed half-way: the live file holds it all
            db, self._file = _open_live(self.path, self.retention.segment_bytes)
            self._db: sqlite3.Connection | None = db
        except BaseException:
            self._rotation.close()
            raise
        self._lock = threading.Lock()
        try:
            self._key = self._open_anchor(db)
            self._rows, self._head = _last(db)  # what this writer knows the chain to be
            self._kept = self._open_segments(db)
            self._rotation.release()
            self._retain_at_open()
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
        self._last_moved = 0
        self._spill = self._open_spill(spill_path, spill_slots)
        self._committer: GroupCommitter[dict[str, Any], int] = GroupCommitter(
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
            spill = Spill(where, self._key, slots=slots)
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

    def spill(self, **fields: Any) -> bool:
        """Keep one row that the trail could not take in the reserved spill, durably; it is
        merged, chained, with the next batch the trail commits.  ``False``: no room."""
        return self._spill is not None and self._spill.add(_stored(fields))

    @property
    def spilled(self) -> int:
        """Rows waiting in the spill."""
        return 0 if self._spill is None else len(self._spill.pending())

    def _refuse_deleted_trail(self) -> None:
        """A head checkpoint without its trail means the trail was deleted: refuse before
        ``_connect`` would create an empty file in its place (a refused start creates
        nothing), saying how many records the checkpoint says existed."""
        if self.path.exists() or not self.anchor.path.exists():
            return
        try:
            checkpoint = self.anchor.read(None)
        except AuditFileError:
            checkpoint = None  # unreadable too: still deleted, count unknown
        held = "records" if checkpoint is None else f"{checkpoint.rows} records"
        raise AuditFileError(
            str(self.path),
            f"deleted: its head checkpoint {self.anchor.path} says the trail held {held}",
            recovery=(
                f"restore {self.path} from a backup; or, to start a new trail and keep the "
                f"evidence, move {self.anchor.path} and {self.anchor.key_path} aside"
            ),
        )

    def _open_anchor(self, db: sqlite3.Connection) -> bytes:
        """Check the database against its checkpoint before appending anything."""
        key = self.anchor.load_key()
        checkpoint = self.anchor.read(key)
        seq, head = _last(db)
        if key is None:
            if checkpoint is not None:
                raise AuditFileError(
                    str(self.anchor.key_path), "missing while the head checkpoint exists",
                    recovery=_recovery(self.path),
                )  # fmt: skip
            if seq:
                raise AuditFileError(
                    str(self.path),
                    f"has {seq} rows but no head checkpoint or key (made before anchoring, "
                    "or both deleted): cannot prove the newest rows were not deleted",
                    recovery=_recovery(self.path),
                )
            key = self.anchor.create_key()
        elif checkpoint is None:
            if seq:
                raise AuditFileError(
                    str(self.anchor.path),
                    "missing: cannot prove the newest rows of the trail were not deleted",
                    recovery=_recovery(self.path),
                )
        else:
            problem = segments.compare(self.path, db, checkpoint)
            if problem is not None:
                raise AuditFileError(str(self.path), problem, recovery=_recovery(self.path))
        self._first = 1 if checkpoint is None else checkpoint.first
        if checkpoint is None or checkpoint.rows != seq:
            self.anchor.write(key, seq, head, first=self._first)
        return key

    def _open_segments(self, db: sqlite3.Connection) -> list[Kept]:
        """The rotated segments, checked in order against the live one and the head."""
        found = [segments.kept(file, n) for n, file in segments.rotated(self.path)]
        live = _link(db)
        order = [(k.path, k.link) for k in found] + [(self.path, live)]
        segments.check_order(self.path, order, self._first)
        if found and found[-1].end != (live.first - 1, live.prev):
            raise AuditFileError(
                str(self.path), f"does not start where {found[-1].path.name} ends (row "
                f"{found[-1].end[0]}): rows of the segment before it missing or rewritten",
                recovery=_recovery(self.path),
            )  # fmt: skip
        self._link = live
        return found

    def _retain_at_open(self) -> None:
        """Finish a retention a crash interrupted and apply retention, alone on the trail
        (two writers would race on the head's oldest segment); else after a rotation."""
        with self._lock:
            if not self._rotation.exclusive(ROTATION_WAIT_S):
                return
            try:
                self._follow()
                for k in [k for k in self._kept if k.n < self._first]:  # marked removed
                    k.path.unlink()
                self._kept = [k for k in self._kept if k.n >= self._first]
                self._retain()
            finally:
                self._rotation.release()

    @contextlib.contextmanager
    def _shared(self) -> Iterator[sqlite3.Connection]:
        """The live segment, current, with the rotation lock held shared (the caller holds
        the writer's lock)."""
        self._rotation.shared()
        try:
            yield self._follow()
        finally:
            self._rotation.release()

    def _live(self) -> sqlite3.Connection:
        assert self._db is not None, "the live segment is open while the rotation lock is held"
        return self._db

    def _follow(self) -> sqlite3.Connection:
        """The live segment (the caller holds the rotation lock): reopened if it is closed,
        another writer rotated it, or another writer's retention removed segments.  The file
        this writer had open must now be a rotated segment (same inode) or one retention
        removed (the head says so); the chain must still hold the last row this writer knew.
        Anything else was deleted or replaced under it: refused."""
        identity = file_identity(self.path)
        current = not self._kept or self._kept[0].path.exists()
        if self._db is not None and identity == self._file and current:
            return self._db
        if identity is None:
            log.error("audit trail %s deleted; refusing to append", self.path)
            raise self._gone()
        if self._db is None and identity == self._file and current:  # closed by this writer
            self._db = _open_live(self.path, self.retention.segment_bytes)[0]
            return self._db
        self._close_live()
        db, file = _open_live(self.path, self.retention.segment_bytes)
        try:
            checkpoint = self.anchor.read(self._key)
            if checkpoint is not None:
                self._first = max(self._first, checkpoint.first)
            if file != self._file:
                renamed = file_identity(segments.numbered(self.path, self._link.n)) == self._file
                if not (renamed or self._link.n < self._first):
                    log.error("audit trail %s replaced; refusing to append", self.path)
                    raise self._gone()
            kept = self._open_segments(db)
            oldest = kept[0].link.first if kept else self._link.first
            if self._rows >= oldest - 1:  # else retention removed the segment holding it
                problem = segments.compare(self.path, db, Checkpoint(self._rows, self._head))
                if problem is not None:
                    raise AuditFileError(str(self.path), problem, recovery=_recovery(self.path))
        except BaseException:
            db.close()
            raise
        self._db, self._file, self._kept = db, file, kept
        self._rows, self._head = _last(db)
        self._live_since = self._first_at(db)
        return db

    def _close_live(self) -> None:
        """Close this writer's live connection (reopened by the next batch): leaving WAL
        mode for a rotation needs every connection but the rotating one's closed."""
        if self._db is not None:
            with contextlib.suppress(sqlite3.Error):
                self._db.close()
            self._db = None

    def _first_at(self, db: sqlite3.Connection) -> float | None:
        """Wall time of the live segment's first row (its age decides rotation)."""
        row = db.execute("SELECT at FROM audit ORDER BY seq LIMIT 1").fetchone()
        return None if row is None else valid_at(row[0])

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
        try:
            future = self.append_later(
                at=at, outcome=outcome, code=code, warning=warning, msg_type=msg_type,
                sender=sender, sender_verified=sender_verified, msg_id=msg_id, durable=True,
            )  # fmt: skip
            assert isinstance(future, Future)
            return future.result()
        except (sqlite3.Error, OSError, RuntimeError, AuditFileError) as exc:
            raise StateUnavailableError(f"audit trail unavailable: {exc}") from None

    def append_later(
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
        on_loop: bool = False,
        durable: bool | None = None,
    ) -> Future[int] | asyncio.Future[int]:
        """Queue one record for the next group commit; the future completes once it is
        durable (``on_loop``: an asyncio future of the running loop, which awaits it before
        answering, holding no thread).  With an outbox, a refusal's (``durable`` defaults
        to ``outcome == "accepted"``) completes once written where a ``kill -9`` cannot
        lose it, durable with the next fsynced batch."""
        row = _stored({
            "at": at, "outcome": outcome, "code": code, "warning": warning,
            "msg_type": msg_type, "sender": sender, "sender_verified": sender_verified,
            "msg_id": msg_id,
        })  # fmt: skip
        if self._outbox is not None:
            sync = outcome == "accepted" if durable is None else durable
            if file_identity(self.path) is None:  # the row would wait for a lost trail
                return _failed(self._gone(), on_loop=on_loop)
            if on_loop:
                return self._outbox.put_async(row, durable=sync)
            return self._outbox.put(row, durable=sync)
        if on_loop:
            return self._committer.enqueue_async(row)
        return self._committer.enqueue(row)

    def _write_batch(self, batch: Sequence[dict[str, Any]], *, sync: bool = False) -> list[int]:
        """Chain and commit a group of rows (spilled ones first, then the outbox's) in one
        write transaction; one head checkpoint; then rotate and retain if due (never
        failing the batch: its rows are written).  Each queued drain answers ``0``."""
        with self._lock:
            self._drain_queued = False  # a row put from now on wakes another drain
            spilled = [] if self._spill is None else self._spill.pending()  # merged first
            direct = [fields for fields in batch if fields is not _DRAIN]
            outbox = self._outbox
            sync = sync or outbox is None or bool(spilled or direct)
            sync = sync or self._clock.monotonic() - self._head_synced >= self.head_sync_s
            with self._shared() as db:  # no rotation meanwhile
                db.execute(f"PRAGMA synchronous={'FULL' if sync else 'NORMAL'}")
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
                    self._checkpoint()
                elif sync:  # the head claims only rows made durable; so does the outbox's delete
                    self._checkpoint(sync=True)
                    self._forget(outbox, done.mark)
                else:
                    self._head_dirty = True
            if spilled:
                self._merged(len(spilled))
            if self._rotation_due():
                self._close_live()  # whichever writer gets the lock rotates: see .segments
                try:
                    why = self._rotate()
                except (sqlite3.Error, OSError, AuditFileError) as exc:
                    why = str(exc)
                if why is not None:
                    self._close_live()
                self._postponed(why)
            elif self._rotates and not self._rotation.alone():
                self._close_live()  # an idle writer's connection would stop the others' rotation
            self._last_moved = done.moved
            if done.moved == DRAIN_BATCH:
                self._wake()  # more waiting: drain on
            seqs = iter(range(done.first, done.rows + 1))
            return [0 if fields is _DRAIN else next(seqs) for fields in batch]

    def _gone(self) -> AuditFileError:
        """The error of a trail deleted or replaced under this writer."""
        return AuditFileError(
            str(self.path), "deleted or replaced under the running writer",
            recovery=f"stop it, restore {self.path} or see antireplay audit reanchor",
        )  # fmt: skip

    def _append(
        self, db: sqlite3.Connection, spilled: list[dict[str, Any]], direct: list[dict[str, Any]]
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
            mark = _mark(db)
            epoch, moved = self._outbox.pending(mark, DRAIN_BATCH)
            mark = (epoch, mark[1] if mark[0] == epoch else 0)
        seq, prev = _last(db)
        rows = [*spilled, *(fields for _, fields in moved), *direct]
        first, values = seq + 1 + len(spilled) + len(moved), []
        for fields in rows:
            seq += 1
            row = {"seq": seq, **fields}
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
        outbox.store.defer_commits()
        self.drain()
        outbox.on_rows = self._wake

    def _roll_back(self, problem: str) -> None:
        """The trail disagrees with the state's record of its head: say so (log, flag,
        counter) and put it on the record, an ``AUDIT_ROLLED_BACK`` row chained now."""
        self.rolled_back, self.rollbacks = problem, self.rollbacks + 1
        log.error("audit trail %s rolled back: %s", self.path, problem)
        row = _stored({"at": self._clock.wall(), "outcome": "alert",
                       "code": consistency.ROLLED_BACK, "warning": problem[:200],
                       "msg_type": None, "sender": None, "sender_verified": False,
                       "msg_id": None})  # fmt: skip
        self._write_batch([row], sync=True)

    def drain(self) -> None:
        """Move everything the outbox holds into the trail now, durably (a database behind
        the trail's mark gets a new epoch first: see :mod:`antireplay.state.outbox`)."""
        if self._outbox is None:
            return
        with self._lock, self._shared() as db:
            mark = _mark(db)
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

    def _postponed(self, why: str | None) -> None:
        """Count a rotation that is due but waits (retried after the next batch); say so
        once per streak, so a reader that never lets go is visible, not silent."""
        if why is None:
            self._waiting = False
            return
        self.rotations_postponed += 1
        if not self._waiting:
            log.warning("audit trail %s: rotation postponed (%s); retried after each batch",
                        self.path, why)  # fmt: skip
        self._waiting = True

    def _checkpoint(self, *, sync: bool = False) -> None:
        """Rewrite the head after a batch (the caller holds the lock); fsync it only once
        ``head_sync_s`` has passed since the last fsync (see the module docstring)."""
        now = self._clock.monotonic()
        sync = sync or now - self._head_synced >= self.head_sync_s
        self.anchor.write(self._key, self._rows, self._head, sync=sync, first=self._first)
        if sync:
            self._head_synced = now
        self._head_dirty = not sync

    def _rotation_due(self) -> bool:
        """The live segment is over its size on disk (its WAL included) or its age; an empty
        live segment never rotates."""
        limit, age = self.retention.segment_bytes, self.retention.segment_age_s
        if self._rows < self._link.first:
            return False
        since = self._live_since
        if age is not None and since is not None and self._clock.wall() - since >= age:
            return True
        return limit is not None and segments.bytes_of(self.path) >= limit

    def _rotation_point(self, step: str) -> None:
        """Called after each step of a rotation (a test stops a real writer there)."""

    def _rotate(self) -> str | None:
        """Make the live segment a rotated one and start the next from its last row (the
        caller holds the lock; the order of steps is argued in :mod:`.segments`); why it
        must wait, if it must."""
        if not self._rotation.exclusive(ROTATION_WAIT_S):
            return "another writer's batch held the trail"
        try:
            n = self._link.n
            self._follow()
            if self._link.n != n:
                return None  # another writer rotated it meanwhile
            return self._rotate_alone()
        finally:
            self._rotation.release()

    def _rotate_alone(self) -> str | None:
        segments.recover(self.path)
        db = self._live()
        if not segments.seal(db):
            return "another connection has the live segment open"
        try:
            db.execute("BEGIN IMMEDIATE")  # another writer waits, then sees the new name
            self._rotation_point("sealed")
            problem = _compare(db, Checkpoint(self._rows, self._head))
            if problem is not None:
                raise AuditFileError(str(self.path), problem, recovery=_recovery(self.path))
            self._rows, self._head = _last(db)  # other writers' rows included
            following = self.anchor.link(self._key, self._link.n + 1, self._rows + 1, self._head)
            mark = _mark(db)
            segments.prepare(self.path, following, mark if mark[0] is not None else None)
            self._rotation_point("prepared")
            old = segments.publish(self.path, self._link.n)
        except BaseException:
            db.execute("ROLLBACK")
            db.execute("PRAGMA journal_mode=WAL")
            raise
        self._rotation_point("published")
        db.execute("ROLLBACK")
        live, identity = _open_live(self.path, self.retention.segment_bytes)
        db.close()
        self._db, self._file = live, identity
        self._kept.append(segments.kept(old, self._link.n))
        self._link, self._live_since = following, None
        self._checkpoint(sync=True)  # a power cut never brings back a head in a rotated segment
        log.info("audit trail %s: segment %d rotated to %s", self.path, following.n - 1, old)
        self._retain()
        return None

    def _retain(self) -> None:
        """Remove the oldest rotated segments past the byte or age budget (the caller holds
        the lock): the head, fsynced, first says they are gone on purpose.  The live segment
        counts as full, as large as the largest rotated one (a segment rotates once a batch
        has taken it past ``segment_bytes``), with its WAL at the most it holds before being
        folded in, so the trail stays within budget until the next rotation."""
        budget, age = self.retention.max_bytes, self.retention.max_age_s
        full = max([self.retention.segment_bytes or 0, *(k.bytes for k in self._kept)])
        wal = _wal_bytes(self.retention.segment_bytes or 0)
        live = max(segments.bytes_of(self.path), full + wal)
        total = sum(k.bytes for k in self._kept) + live
        horizon = None if age is None else self._clock.wall() - age
        doomed = 0
        for k in self._kept:
            old = horizon is not None and k.last_at is not None and k.last_at < horizon
            if not (old or (budget is not None and total > budget)):
                break
            total -= k.bytes
            doomed += 1
        if not doomed:
            return
        gone, self._kept = self._kept[:doomed], self._kept[doomed:]
        self._first = gone[-1].n + 1
        self._checkpoint(sync=True)
        self._rotation_point("retaining")
        for k in gone:  # oldest first: a crash leaves the rest in a row
            k.path.unlink(missing_ok=True)
        log.info("audit trail %s: segments %d-%d removed by retention", self.path, gone[0].n,
                 gone[-1].n)  # fmt: skip

    def usage(self) -> TrailUsage:
        """Bytes on disk across segments (WAL included), segments kept, oldest row's time
        (the files on disk, which other writers rotate and retain too; the oldest row's
        time as this writer last saw it)."""
        with self._lock:
            files = [file for _, file in segments.rotated(self.path)]
            live = segments.bytes_of(self.path)
            oldest = next((k.first_at for k in self._kept if k.first_at is not None),
                          self._live_since)  # fmt: skip
        return TrailUsage(sum(map(segments.bytes_of, files)) + live, len(files) + 1, oldest)

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
            return live + sum(_rows_in(k.path) for k in self._kept)

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


def _open_live(
    path: Path, segment_bytes: int | None
) -> tuple[sqlite3.Connection, tuple[int, int] | None]:
    """The live segment and the file it is (not just its name).  With a segment size, its
    WAL is folded in and cut back once it holds a quarter of one (at most SQLite's default
    1000 pages), so the bytes on disk, not only the rows, decide rotation and the budget."""
    db = _connect(path, read_only=False)
    if segment_bytes is not None:
        page = int(db.execute("PRAGMA page_size").fetchone()[0])
        pages = max(1, _wal_bytes(segment_bytes) // page)
        db.execute(f"PRAGMA wal_autocheckpoint={pages}")
        db.execute(f"PRAGMA journal_size_limit={pages * page}")
    return db, file_identity(path)


def _wal_bytes(segment_bytes: int) -> int:
    """What the live segment's WAL holds before it is folded in (and retention keeps room
    for): a quarter segment, at most SQLite's default checkpoint of 1000 4-KiB pages."""
    return min(segment_bytes // 4, 1000 * 4096)


def _rows_in(path: Path) -> int:
    with contextlib.suppress(FileNotFoundError, AuditFileError):
        db = _connect(path, read_only=True)
        try:
            return int(db.execute("SELECT count(*) FROM audit").fetchone()[0])
        finally:
            db.close()
    return 0


def _mark(db: sqlite3.Connection) -> Mark:
    """The outbox epoch and highest id the trail holds (``(None, 0)``: never drained)."""
    try:
        row = db.execute("SELECT epoch, moved FROM outbox_moved").fetchone()
    except sqlite3.OperationalError:  # no such table: never drained into
        return None, 0
    return (None, 0) if row is None else (row[0], int(row[1]))


def _failed(error: BaseException, *, on_loop: bool) -> Future[int] | asyncio.Future[int]:
    """A queued row's future that has already failed with ``error``."""
    future: Future[int] | asyncio.Future[int]
    future = asyncio.get_running_loop().create_future() if on_loop else Future()
    future.set_exception(error)
    return future
