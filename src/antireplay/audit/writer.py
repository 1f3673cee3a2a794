"""The audit writer: group-committed, hash-chained appends with an anchored head.

See :mod:`antireplay.audit` for the theory of operation.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sqlite3
import threading
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from antireplay.audit.chain import (
    _FIELDS,
    _TAIL,
    GENESIS,
    Checkpoint,
    HeadAnchor,
    Record,
    _compare,
    _connect,
    _digest,
    _last,
    _records,
    _recovery,
    sanitize,
)
from antireplay.audit.spill import SLOTS, Spill
from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import AuditFileError, StateUnavailableError
from antireplay.state.durable import file_identity
from antireplay.state.groupcommit import GroupCommitter

log = logging.getLogger("antireplay.audit")


@dataclass(frozen=True)
class TrailUsage:
    """What the trail holds on disk: bytes, segments, and the time of its oldest row."""

    bytes: int
    segments: int
    oldest: float | None


def _stored(fields: dict[str, Any]) -> dict[str, Any]:
    """One row as stored: identifiers sanitized, the flag an integer."""
    return {
        **fields, "sender": sanitize(fields["sender"]),
        "sender_verified": int(fields["sender_verified"]), "msg_id": sanitize(fields["msg_id"]),
    }  # fmt: skip


class AuditLog:
    """Append-only, hash-chained audit trail in one SQLite file, head anchored outside it."""

    def __init__(
        self,
        path: str | Path,
        *,
        head_key: str | Path | None = None,
        head_path: str | Path | None = None,
        head_sync_s: float = 1.0,
        clock: Clock | None = None,
        spill_path: str | Path | None = None,
        spill_slots: int = SLOTS,
    ) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.anchor = HeadAnchor(self.path, Path(head_key) if head_key else None,
                                 Path(head_path) if head_path else None)  # fmt: skip
        #: Longest a checkpoint stays un-fsynced while rows are appended (power cuts only).
        self.head_sync_s = head_sync_s
        self._clock = resolve(clock)
        self._head_synced = self._clock.monotonic()
        self._head_dirty = False
        self._refuse_deleted_trail()
        self._db = _connect(self.path, read_only=False)
        self._file = file_identity(self.path)  # the file this writer appends to, not just its name
        self._lock = threading.Lock()
        try:
            self._key = self._open_anchor()
        except BaseException:
            self._db.close()
            raise
        self._rows, self._head = _last(self._db)  # what this writer knows the chain to be
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

    def usage(self) -> TrailUsage:
        """Disk used by the trail (its file, WAL and head), its segments and oldest row."""
        size = 0
        for name in ("", "-wal", "-shm"):
            with contextlib.suppress(OSError):
                size += Path(f"{self.path}{name}").stat().st_size
        with self._lock:
            first = self._db.execute("SELECT at FROM audit ORDER BY seq LIMIT 1").fetchone()
        return TrailUsage(size, 1, None if first is None else float(first[0]))

    # --------------------------------------------------------------------------------------------

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
            problem = _compare(self._db, checkpoint)
            if problem is not None:
                raise AuditFileError(str(self.path), problem, recovery=_recovery(self.path))
        if checkpoint is None or checkpoint.rows != seq:
            self.anchor.write(key, seq, head)
        return key

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
        """Chain and commit a group of rows in one write transaction; one head checkpoint."""
        with self._lock:
            spilled = [] if self._spill is None else self._spill.pending()  # merged first
            db = self._db
            if file_identity(self.path) != self._file:  # rows written now would be lost with it
                log.error("audit trail %s deleted or replaced; refusing to append", self.path)
                raise AuditFileError(
                    str(self.path), "deleted or replaced under the running writer",
                    recovery=f"stop it, restore {self.path} or see antireplay audit reanchor",
                )  # fmt: skip
            db.execute("BEGIN IMMEDIATE")
            try:
                # Rows deleted or rewritten under a running writer must not be adopted by
                # its next checkpoint: the chain must still hold what this writer wrote
                # (another writer may have extended it).
                problem = _compare(db, Checkpoint(self._rows, self._head))
                if problem is not None:
                    log.error("audit trail %s %s; refusing to append", self.path, problem)
                    raise AuditFileError(str(self.path), problem, recovery=_recovery(self.path))
                last = db.execute(
                    "SELECT seq, hash FROM audit ORDER BY seq DESC LIMIT 1"
                ).fetchone()
                seq, prev = (0, GENESIS) if last is None else (last[0], last[1])
                first, values = seq + 1, []
                for fields in [*spilled, *batch]:
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
            self._checkpoint()
            if spilled:
                self._merged(len(spilled))
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

    def _checkpoint(self) -> None:
        """Rewrite the head after a batch (the caller holds the lock); fsync it only once
        ``head_sync_s`` has passed since the last fsync (see the module docstring)."""
        now = self._clock.monotonic()
        sync = now - self._head_synced >= self.head_sync_s
        self.anchor.write(self._key, self._rows, self._head, sync=sync)
        if sync:
            self._head_synced = now
        self._head_dirty = not sync

    def tail(self, n: int = 20) -> list[Record]:
        with self._lock:
            return _records(self._db.execute(_TAIL, (n,)).fetchall())

    def count(self) -> int:
        with self._lock:
            return int(self._db.execute("SELECT count(*) FROM audit").fetchone()[0])

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
                    self.anchor.write(self._key, self._rows, self._head, sync=True)
                    self._head_dirty = False
            except OSError as exc:  # the head on disk may lag after a power cut: under-claims
                log.warning("audit head %s not made durable at close: %s", self.anchor.path, exc)
            finally:
                self._db.close()
                if self._spill is not None:
                    self._spill.close()
