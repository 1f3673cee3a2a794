"""The audit writer: group-committed, hash-chained appends with an anchored head.

See :mod:`antireplay.audit` for the theory of operation and :mod:`.segments` for how
the trail rotates and what retention removes.  Each batch is one transaction in
:meth:`AuditLog._write_batch`; rotation and retention run after it, under the same lock,
and never fail the batch (its rows are durable: a failed rotation is retried next batch).
Rows waiting in the ESTOP spill (:mod:`.spill`) are merged first in each batch.

Size: the writer, the spill merge, rotation and retention share one lock and one batch.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sqlite3
import threading
from collections.abc import Sequence
from concurrent.futures import Future
from os import PathLike
from pathlib import Path
from typing import Any

from antireplay.audit import segments
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

log = logging.getLogger("antireplay.audit")


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
        self._clock = resolve(clock)
        self._head_synced = self._clock.monotonic()
        self._head_dirty = False
        #: Rotations that were due but had to wait (another writer or reader had the trail).
        self.rotations_postponed = 0
        self._waiting = False
        self._refuse_deleted_trail()
        self._rotation = segments.RotationLock(self.path)  # no other writer is rotating now
        try:
            segments.recover(self.path)  # a rotation killed half-way: the live file holds it all
            self._db, self._file = _open_live(self.path, self.retention.segment_bytes)
        except BaseException:
            self._rotation.close()
            raise
        self._lock = threading.Lock()
        try:
            self._key = self._open_anchor()
            self._rows, self._head = _last(self._db)  # what this writer knows the chain to be
            self._kept = self._open_segments()
        except BaseException as exc:
            self._db.close()
            self._rotation.close()
            if isinstance(exc, sqlite3.DatabaseError):
                raise AuditFileError(
                    str(self.path),
                    f"not a usable audit segment ({exc})",
                    recovery=_recovery(self.path),
                ) from None
            raise
        self._live_since = self._first_at()
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

    def _open_anchor(self) -> bytes:
        """Check the database against its checkpoint before appending anything."""
        key = self.anchor.load_key()
        checkpoint = self.anchor.read(key)
        seq, head = _last(self._db)
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
            problem = segments.compare(self.path, self._db, checkpoint)
            if problem is not None:
                raise AuditFileError(str(self.path), problem, recovery=_recovery(self.path))
        self._first = 1 if checkpoint is None else checkpoint.first
        if checkpoint is None or checkpoint.rows != seq:
            self.anchor.write(key, seq, head, first=self._first)
        return key

    def _open_segments(self) -> list[Kept]:
        """The rotated segments, checked in order against the live one and the head; then,
        if no other writer has the trail open, a retention a crash interrupted is finished
        and retention applied (two writers would race on the head's oldest segment)."""
        found = [segments.kept(file, n) for n, file in segments.rotated(self.path)]
        live = _link(self._db)
        order = [(k.path, k.link) for k in found] + [(self.path, live)]
        segments.check_order(self.path, order, self._first)
        if found and found[-1].end != (live.first - 1, live.prev):
            raise AuditFileError(
                str(self.path), f"does not start where {found[-1].path.name} ends (row "
                f"{found[-1].end[0]}): rows of the segment before it missing or rewritten",
                recovery=_recovery(self.path),
            )  # fmt: skip
        self._link = live
        with self._lock:
            self._kept = found
            if self._rotation.exclusive():
                try:
                    for k in [k for k in found if k.n < self._first]:  # marked removed
                        k.path.unlink()
                    self._kept = [k for k in found if k.n >= self._first]
                    self._retain()
                finally:
                    self._rotation.shared()
        return self._kept

    def _first_at(self) -> float | None:
        """Wall time of the live segment's first row (its age decides rotation)."""
        row = self._db.execute("SELECT at FROM audit ORDER BY seq LIMIT 1").fetchone()
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
                sender=sender, sender_verified=sender_verified, msg_id=msg_id,
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
    ) -> Future[int] | asyncio.Future[int]:
        """Queue one record for the next group commit; the future completes once it is
        durable (``on_loop``: an asyncio future of the running loop, which awaits it before
        answering, holding no thread)."""
        row = _stored({
            "at": at, "outcome": outcome, "code": code, "warning": warning,
            "msg_type": msg_type, "sender": sender, "sender_verified": sender_verified,
            "msg_id": msg_id,
        })  # fmt: skip
        if on_loop:
            return self._committer.enqueue_async(row)
        return self._committer.enqueue(row)

    def _write_batch(self, batch: Sequence[dict[str, Any]]) -> list[int]:
        """Chain and commit a group of rows in one write transaction; one head checkpoint;
        then rotate and retain if due (never failing the batch: its rows are durable)."""
        with self._lock:
            spilled = [] if self._spill is None else self._spill.pending()  # merged first
            db = self._db
            db.execute("BEGIN IMMEDIATE")  # then the name: another writer rotates holding this lock
            try:
                if file_identity(self.path) != self._file:  # rows written now would be lost
                    log.error("audit trail %s deleted or replaced; refusing to append", self.path)
                    raise AuditFileError(
                        str(self.path), "deleted or replaced under the running writer",
                        recovery=f"stop it, restore {self.path} or see antireplay audit reanchor",
                    )  # fmt: skip
                # Rows deleted or rewritten under a running writer must not be adopted by
                # its next checkpoint: the chain must still hold what this writer wrote
                # (another writer may have extended it).
                problem = _compare(db, Checkpoint(self._rows, self._head))
                if problem is not None:
                    log.error("audit trail %s %s; refusing to append", self.path, problem)
                    raise AuditFileError(str(self.path), problem, recovery=_recovery(self.path))
                seq, prev = _last(db)
                first, values, rows = seq + 1, [], [*spilled, *batch]
                for fields in rows:
                    seq += 1
                    row = {"seq": seq, **fields}
                    digest = _digest(prev, row)
                    values.append((*(row[f] for f in _FIELDS), prev, digest))
                    prev = digest
                db.executemany("INSERT INTO audit VALUES (?,?,?,?,?,?,?,?,?,?,?)", values)
                db.execute("COMMIT")
            except BaseException:
                with contextlib.suppress(sqlite3.Error):  # a full disk: SQLite rolled back
                    db.execute("ROLLBACK")
                raise
            self._rows, self._head = seq, prev
            if self._live_since is None and rows:
                self._live_since = valid_at(rows[0]["at"])
            self._checkpoint()
            if spilled:
                self._merged(len(spilled))
            if self._rotation_due():
                try:
                    why = self._rotate()
                except (sqlite3.Error, OSError, AuditFileError) as exc:
                    why = str(exc)
                self._postponed(why)
            return list(range(first + len(spilled), seq + 1))

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
        if not self._rotation.exclusive():
            return "another writer has the trail open"
        try:
            return self._rotate_alone()
        finally:
            self._rotation.shared()

    def _rotate_alone(self) -> str | None:
        segments.recover(self.path)
        if not segments.seal(self._db):
            return "another connection has the live segment open"
        try:
            self._db.execute("BEGIN IMMEDIATE")  # another writer waits, then sees the new name
            self._rotation_point("sealed")
            following = self.anchor.link(self._key, self._link.n + 1, self._rows + 1, self._head)
            segments.prepare(self.path, following)
            self._rotation_point("prepared")
            old = segments.publish(self.path, self._link.n)
        except BaseException:
            self._db.execute("ROLLBACK")
            self._db.execute("PRAGMA journal_mode=WAL")
            raise
        self._rotation_point("published")
        self._db.execute("ROLLBACK")
        live, identity = _open_live(self.path, self.retention.segment_bytes)
        self._db.close()
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
        has taken it past ``segment_bytes``), so the trail stays within budget until the next
        rotation."""
        budget, age = self.retention.max_bytes, self.retention.max_age_s
        full = max([self.retention.segment_bytes or 0, *(k.bytes for k in self._kept)])
        live = max(segments.bytes_of(self.path), full)
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
        """Bytes on disk across segments (WAL included), segments kept, oldest row's time."""
        with self._lock:
            kept = list(self._kept)
            live = segments.bytes_of(self.path)
            oldest = next((k.first_at for k in kept if k.first_at is not None), self._live_since)
        return TrailUsage(sum(k.bytes for k in kept) + live, len(kept) + 1, oldest)

    def tail(self, n: int = 20) -> list[Record]:
        """The newest ``n`` records across segments (read-only connections)."""
        return segments.newest(self.path, n)

    def count(self) -> int:
        """Records kept across segments."""
        with self._lock:
            live = int(self._db.execute("SELECT count(*) FROM audit").fetchone()[0])
            return live + sum(_rows_in(k.path) for k in self._kept)

    @property
    def group_commit(self) -> GroupCommitter[Any, Any]:
        """The writer that batches this file's commits (its counters feed /metrics)."""
        return self._committer

    def close(self) -> None:
        """Write what is queued (and what is spilled, if the trail takes it now), make the
        head durable, then close."""
        self._committer.close()
        if self.spilled:
            with contextlib.suppress(sqlite3.Error, OSError, AuditFileError):
                self._write_batch([])  # else merged at the next start
        with self._lock:
            try:
                if self._head_dirty:
                    self.anchor.write(self._key, self._rows, self._head, sync=True,
                                      first=self._first)  # fmt: skip
                    self._head_dirty = False
            except OSError as exc:  # the head on disk may lag after a power cut: under-claims
                log.warning("audit head %s not made durable at close: %s", self.anchor.path, exc)
            finally:
                self._db.close()
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
        pages = max(1, min(1000, segment_bytes // page // 4))
        db.execute(f"PRAGMA wal_autocheckpoint={pages}")
        db.execute(f"PRAGMA journal_size_limit={pages * page}")
    return db, file_identity(path)


def _rows_in(path: Path) -> int:
    with contextlib.suppress(FileNotFoundError, AuditFileError):
        db = _connect(path, read_only=True)
        try:
            return int(db.execute("SELECT count(*) FROM audit").fetchone()[0])
        finally:
            db.close()
    return 0
