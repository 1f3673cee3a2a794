"""The trail's files over a writer's life: checked at open, followed, rotated, retained.

At open the trail must match its head checkpoint (a trail deleted under its checkpoint,
rows missing or rewritten, a key or checkpoint missing: refused, naming the recovery).
How segments chain, what each rotation step leaves on disk and why the steps come in that
order is in :mod:`.segments`; this is the writer's side of it, run under the writer's
lock.  :class:`SegmentLifecycle` holds the live connection, the rotated segments kept and
the :class:`~.segments.RotationLock`: :meth:`~SegmentLifecycle._shared` hands a batch the
live segment with the lock held shared (reopened when another writer rotated it, refused
when it was deleted or replaced: :meth:`~SegmentLifecycle._follow`); after each batch
:meth:`~SegmentLifecycle._after_batch` rotates a segment past its size or age, taking the
lock exclusively for at most ``ROTATION_WAIT_S`` (else postponed to the next batch and
counted), and :meth:`~SegmentLifecycle._retain` removes the oldest segments past the byte
or age budget, the head (fsynced) first recording the cut.  The writer
(:class:`~.writer.AuditLog`) supplies the chain head (``_rows``, ``_head``), its key and
:meth:`~SegmentLifecycle._checkpoint`.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path

from antireplay.audit import segments
from antireplay.audit.chain import (
    Checkpoint,
    HeadAnchor,
    HeadKey,
    Link,
    _compare,
    _connect,
    _last,
    _link,
    _recovery,
    valid_at,
)
from antireplay.audit.segments import Kept, Retention, TrailUsage
from antireplay.core.clock import Clock
from antireplay.core.errors import AuditFileError
from antireplay.state.durable import file_identity

log = logging.getLogger("antireplay.audit")
#: Longest a due rotation waits for other writers' batches in flight (then postponed).
ROTATION_WAIT_S = 0.5


class SegmentLifecycle:
    """The live segment and the rotated ones of one writer (see the module docstring)."""

    path: Path
    anchor: HeadAnchor
    retention: Retention
    _clock: Clock
    _lock: threading.Lock
    _key: HeadKey
    _rows: int
    _head: str
    _first: int
    _db: sqlite3.Connection | None
    _file: tuple[int, int] | None
    _kept: list[Kept]
    _link: Link
    _live_since: float | None

    def _open_lifecycle(self) -> sqlite3.Connection:
        """Take the rotation lock shared, recover a rotation killed half-way (the live file
        holds it all) and open the live segment; the lock stays held (shared) for the
        writer's open-time checks, which end with :meth:`_opened`."""
        self._rotates = self.retention.segment_bytes is not None or (
            self.retention.segment_age_s is not None
        )
        #: Rotations that were due but had to wait (another writer or reader had the trail).
        self.rotations_postponed = 0
        self._waiting = False
        self._rotation = segments.RotationLock(self.path)  # shared: no writer is rotating now
        try:
            segments.recover(self.path)
            db, self._file = _open_live(self.path, self.retention.segment_bytes)
        except BaseException:
            self._rotation.close()
            raise
        self._db = db
        return db

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

    def _open_anchor(self, db: sqlite3.Connection) -> HeadKey:
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

    def _opened(self, db: sqlite3.Connection) -> None:
        """The head is checked: check the rotated segments, let go of the lock, and apply
        retention (alone on the trail, if it can be)."""
        self._kept = self._open_segments(db)
        self._rotation.release()
        self._retain_at_open()

    def _checkpoint(self, *, sync: bool = False) -> None:
        """Write the head (the writer's)."""
        raise NotImplementedError

    def _after_batch(self) -> None:
        """After a batch (the caller holds the writer's lock): rotate if due (never failing
        the batch: a rotation that fails or must wait is retried after the next one); a
        writer that is not alone closes its connection, which would stop the others'."""
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
            self._close_live()

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

    def _gone(self) -> AuditFileError:
        """The error of a trail deleted or replaced under this writer."""
        return AuditFileError(
            str(self.path), "deleted or replaced under the running writer",
            recovery=f"stop it, restore {self.path} or see antireplay audit reanchor",
        )  # fmt: skip

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
            mark = mark_of(db)
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


def rows_in(path: Path) -> int:
    with contextlib.suppress(FileNotFoundError, AuditFileError):
        db = _connect(path, read_only=True)
        try:
            return int(db.execute("SELECT count(*) FROM audit").fetchone()[0])
        finally:
            db.close()
    return 0


def mark_of(db: sqlite3.Connection) -> tuple[str | None, int]:
    """The outbox epoch and highest id the trail holds (``(None, 0)``: never drained)."""
    try:
        row = db.execute("SELECT epoch, moved FROM outbox_moved").fetchone()
    except sqlite3.OperationalError:  # no such table: never drained into
        return None, 0
    return (None, 0) if row is None else (row[0], int(row[1]))
