"""Segments: one audit trail as a sequence of SQLite files, rotated, retained, still one chain.

Theory of operation
-------------------
``PATH`` (the trail's name, as always) is the live segment; rotated segments sit beside it
as ``PATH.000041`` (six or more digits: the segment's number, so names sort in chain order
and ``ls`` shows the trail).  Rows keep one sequence across segments; segment ``n+1``'s
first row chains from segment ``n``'s last hash, and its ``segment`` row (its
:class:`~antireplay.audit.chain.Link`: number, first row, that hash) is MACed with the
head key, so the oldest segment kept starts at a proven cut point.  A trail written before
segments is segment 1.

Rotation (by one writer, holding its lock and :class:`RotationLock` exclusively, between
batches) never leaves ``PATH`` missing, and each step is a state :func:`recover` or the
verifier understands: the live segment leaves WAL mode (one self-contained file; another
open connection postpones rotation), the next segment is written whole to ``PATH.next``
and fsynced, ``PATH`` is hard-linked to its rotated name (a ``kill -9`` here leaves the
same file under two names: the rotated name is dropped), then ``PATH.next`` is renamed over
``PATH``, the directory fsynced, and the head (whose row the new segment's link names)
fsynced.  Retention removes whole segments, oldest first, never the live one: the head,
fsynced, first records the oldest segment kept, then the files go, so a segment missing
above that mark (a gap, or the newest ones) is tampering and refused by name.

Several writers (``serve --workers N``) share one trail: each holds the lock shared only
around a batch, so a rotation waits at most for the batches in flight.  Leaving WAL mode
needs every other connection closed, so a writer that is not alone (``PATH.writers``)
closes its live connection after each batch, and one whose batch finds rotation due tries
to rotate; whoever gets the lock first rotates, the others find the file they had open under
a rotated name at their next batch (:meth:`~.writer.AuditLog._follow`: same inode as
``PATH.NNNNNN``, or a segment retention removed per the head) and reopen the live one; a
file that is neither was deleted or replaced, and is refused.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path

from antireplay.audit.chain import (
    _TAIL,
    FIRST_LINK,
    GENESIS,
    Checkpoint,
    Link,
    Record,
    _compare,
    _connect,
    _last,
    _link,
    _records,
    valid_at,
)
from antireplay.core.errors import AuditFileError
from antireplay.state.durable import file_identity

_NUMBERED = re.compile(r"\.(\d{6,})")


@dataclass(frozen=True)
class Retention:
    """When the live segment rotates and which rotated segments are removed (``None``:
    no limit).  Bytes are bytes on disk, the live segment's WAL included; retention counts
    the live segment as full, with a full WAL, so the trail stays within ``max_bytes``."""

    segment_bytes: int | None = None
    segment_age_s: float | None = None
    max_bytes: int | None = None
    max_age_s: float | None = None


@dataclass(frozen=True)
class TrailUsage:
    """What the trail holds on disk now (for metrics and the disk-pressure checks)."""

    bytes: int
    segments: int
    #: Wall time of the oldest row kept, ``None`` for an empty trail.
    oldest: float | None


@dataclass(frozen=True)
class Kept:
    """A rotated segment the writer keeps track of: where it starts and ends (checked
    against its neighbours at open) and what retention needs."""

    n: int
    path: Path
    bytes: int
    first_at: float | None
    last_at: float | None
    link: Link = FIRST_LINK
    #: (seq, hash) of its last row.
    end: tuple[int, str] = (0, GENESIS)


class RotationLock:
    """``PATH.lock``: a writer holds it shared while it opens the trail or writes a batch;
    a rotation (or retention) holds it exclusive, so nobody writes, opens or recovers a
    half-done rotation meanwhile.  Held by nobody between batches."""

    def __init__(self, path: Path) -> None:
        self.path = path.with_name(path.name + ".lock")
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        self.shared()  # waits out a rotation in progress
        #: ``PATH.writers``, held shared for the writer's lifetime: who else is open.
        self._open = os.open(path.with_name(path.name + ".writers"), os.O_RDWR | os.O_CREAT, 0o600)
        fcntl.flock(self._open, fcntl.LOCK_SH)

    def alone(self) -> bool:
        """No other writer has the trail open (then this one may keep its connection)."""
        try:
            fcntl.flock(self._open, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        finally:
            fcntl.flock(self._open, fcntl.LOCK_SH)
        return True

    def exclusive(self, wait_s: float = 0.0) -> bool:
        """Take it for a rotation, waiting up to ``wait_s`` for batches in flight;
        ``False`` (and no longer held) if they do not end in time."""
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return True
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    self.release()
                    return False
                time.sleep(0.001)

    def shared(self) -> None:
        fcntl.flock(self._fd, fcntl.LOCK_SH)

    def release(self) -> None:
        fcntl.flock(self._fd, fcntl.LOCK_UN)

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            os.close(self._open)
            self._fd = -1


def numbered(path: Path, n: int) -> Path:
    """The name segment ``n`` gets when it is rotated out."""
    return path.with_name(f"{path.name}.{n:06d}")


def next_path(path: Path) -> Path:
    """Where the next segment is written whole before it becomes the live one."""
    return path.with_name(path.name + ".next")


def rotated(path: Path) -> list[tuple[int, Path]]:
    """The rotated segments beside ``path``, by number; a rotated name that is the live
    file itself (a rotation killed after its hard link) is not one."""
    live = file_identity(path)
    found = []
    for entry in path.parent.glob(f"{glob_escape(path.name)}.*"):
        match = _NUMBERED.fullmatch(entry.name[len(path.name) :])
        if match and (live is None or file_identity(entry) != live):
            found.append((int(match.group(1)), entry))
    return sorted(found)


def glob_escape(name: str) -> str:
    return re.sub(r"([*?\[])", r"[\1]", name)


def sync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def bytes_of(path: Path) -> int:
    """A segment's bytes on disk, its WAL included (0 for a file gone meanwhile)."""
    total = 0
    for name in (path, path.with_name(path.name + "-wal")):
        with contextlib.suppress(FileNotFoundError):
            total += name.stat().st_size
    return total


def newest(path: Path, n: int) -> list[Record]:
    """The newest ``n`` records: the live segment's, then rotated ones', newest first, until
    ``n`` are found.  The live segment's read transaction stays open meanwhile, so it cannot
    rotate (nor retention run) under the read; a rotated segment gone anyway ends the search."""
    live = _connect(path, read_only=True)
    try:
        live.execute("BEGIN")  # held to the end: a rotation waits for it
        found = _records(live.execute(_TAIL, (n,)).fetchall())
        for _, file in reversed(rotated(path)):
            if len(found) >= n or not file.exists():
                break
            db = _connect(file, read_only=True)
            try:
                found = _records(db.execute(_TAIL, (n - len(found),)).fetchall()) + found
            finally:
                db.close()
    finally:
        live.close()
    return found


def compare(path: Path, live: sqlite3.Connection, checkpoint: Checkpoint) -> str | None:
    """The head checkpoint against the live segment, or against the rotated segment holding
    its row (an older head a power cut brought back just after a rotation)."""
    if checkpoint.rows >= _link(live).first - 1:
        return _compare(live, checkpoint)
    for _, file in reversed(rotated(path)):
        db = _connect(file, read_only=True)
        try:
            if checkpoint.rows >= _link(db).first - 1:
                return _compare(db, checkpoint)
        finally:
            db.close()
    return f"truncated: the head checkpoint covers row {checkpoint.rows}, no segment holds it"


#: The table where a trail drained from an outbox keeps the highest id it moved.
MARK_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS outbox_moved"
    " (id INTEGER PRIMARY KEY CHECK (id = 1), epoch TEXT, moved INTEGER NOT NULL)"
)


def recover(path: Path) -> None:
    """Undo a rotation a ``kill -9`` interrupted: drop a stale ``PATH.next`` and a rotated
    name hard-linked to the live file (the live file still holds every row)."""
    with contextlib.suppress(FileNotFoundError):
        next_path(path).unlink()
    live = file_identity(path)
    for entry in path.parent.glob(f"{glob_escape(path.name)}.*"):
        if _NUMBERED.fullmatch(entry.name[len(path.name) :]) and file_identity(entry) == live:
            entry.unlink()


def kept(path: Path, n: int) -> Kept:
    """What the writer needs to know of rotated segment ``n`` (read once, then cached)."""
    db = _connect(path, read_only=True)
    try:
        ends = db.execute(
            "SELECT (SELECT at FROM audit ORDER BY seq LIMIT 1),"
            " (SELECT at FROM audit ORDER BY seq DESC LIMIT 1)"
        ).fetchone()
        link, end = _link(db), _last(db)
    except sqlite3.DatabaseError as exc:
        raise AuditFileError(
            str(path),
            f"not a usable audit segment ({exc})",
            recovery=f"antireplay audit verify {path}",
        ) from None
    finally:
        db.close()
    return Kept(n, path, bytes_of(path), valid_at(ends[0]), valid_at(ends[1]), link, end)


def seal(db: sqlite3.Connection) -> bool:
    """Fold the live segment's WAL into it and leave WAL mode, so the file is the whole
    segment under any name; ``False`` while another connection has it open."""
    try:
        mode = db.execute("PRAGMA journal_mode=DELETE").fetchone()[0]
    except sqlite3.OperationalError:  # locked by another connection
        return False
    return str(mode).lower() == "delete"


def prepare(path: Path, link: Link, moved: tuple[str | None, int] | None = None) -> None:
    """Write the next segment, whole and fsynced, at ``PATH.next`` (not yet live);
    ``moved``: the outbox mark it carries on (:mod:`.writer`)."""
    target = next_path(path)
    with contextlib.suppress(FileNotFoundError):
        target.unlink()
    db = _connect(target, read_only=False)
    try:
        db.execute("PRAGMA journal_mode=DELETE")  # no WAL named after a temporary file
        db.execute(
            "INSERT INTO segment VALUES (?,?,?,?)", (link.n, link.first, link.prev, link.mac)
        )
        if moved is not None:
            db.execute(MARK_SCHEMA)
            db.execute("INSERT INTO outbox_moved VALUES (1, ?, ?)", moved)
    finally:
        db.close()


def publish(path: Path, n: int) -> Path:
    """Give the live segment its rotated name, then make ``PATH.next`` the live one."""
    old = numbered(path, n)
    os.link(path, old)  # fails if the name is taken: never overwrite a segment
    os.replace(next_path(path), path)
    sync_dir(path.parent)
    return old


def relink(file: Path, link: Link) -> None:
    """Rewrite a segment's link (``audit reanchor`` with a new key), in its journal mode."""
    db = sqlite3.connect(file)
    try:
        with db:
            db.execute("DELETE FROM segment")
            db.execute(
                "INSERT INTO segment VALUES (?,?,?,?)", (link.n, link.first, link.prev, link.mac)
            )
    finally:
        db.close()


def check_order(path: Path, links: list[tuple[Path, Link]], first: int) -> None:
    """Refuse a trail whose segments are not ``first..live`` in a row: a rotated file that
    holds another segment (renamed, swapped), a gap (a middle segment deleted), or
    segments missing above the oldest one retention kept (recent ones deleted)."""
    restore = "restore it from a backup (retention only ever removes the oldest segments)"
    for file, link in links[:-1]:
        match = _NUMBERED.fullmatch(file.name[len(path.name) :])
        if match and int(match.group(1)) != link.n:
            raise AuditFileError(
                str(file), f"holds segment {link.n}, not {int(match.group(1))}: renamed or swapped",
                recovery=f"give each segment back its own name ({path.name}.{link.n:06d}); "
                f"then antireplay audit verify {path}",
            )  # fmt: skip
    expected = min(first, links[0][1].n)
    for file, link in links:
        if link.n != expected:
            missing = numbered(path, expected)
            what = "deleted" if link.n > expected else "out of order"
            raise AuditFileError(
                str(missing), f"{what}: segment {expected} of the trail is missing before {file}",
                recovery=restore if link.n > expected else f"antireplay audit verify {path}",
            )  # fmt: skip
        expected += 1
