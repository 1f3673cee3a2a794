"""The audit trail: append-only, hash-chained records in SQLite; never the payload.

Theory of operation
-------------------
Every accepted message and every rejection that matters is one row:
time, outcome, code, warning, message type, sender (the authenticated owner,
or the claimed ``sender`` marked unverified) and a sanitized msg_id.  Attacker
strings are never stored raw: an identifier is kept only if it is at most 64
characters of ``[A-Za-z0-9._:@/-]``; anything else is replaced by
``sha256:<first 16 hex>`` of it, so no log line can be forged with newlines,
escapes or terminal codes, and nothing from ``params`` is ever written.

Each row stores ``hash = SHA-256(prev_hash | canonical JSON of the row)``; the
first row chains from 64 zeros.  :func:`verify` recomputes the chain and
reports the first broken link, so an edited, deleted or reordered row is
detected.  Writes use WAL with ``synchronous=FULL``: ``append`` returns after
the record is durable, so a crash never loses a committed record.  Appends are
**group-committed** (:mod:`antireplay.state.groupcommit`): the rows of concurrent
callers are chained and committed in one transaction with one fsync and one
head checkpoint, each caller answered once its own row is durable, so a replay
flood costs one fsync per batch of rejections, not one each.

**The head is anchored outside the database.**  The chain alone cannot show
that its newest rows were deleted, and whoever can write the database can
recompute a whole new chain.  So, like a transparency log's signed tree head,
the head ``(rows, last hash)`` is MACed (HMAC-SHA256) with a key that is not in
the database and checkpointed to a file outside it (:class:`HeadAnchor`):
``PATH.key`` (32 random bytes as hex, mode 0600, created on first use; or a
configured path, ideally somewhere the database's writers cannot read) and
``PATH.head``, one fixed-size record).  The checkpoint names the last row and
is rewritten in place after every commit batch, so it survives a ``kill -9``
at once (the page cache outlives the process), but it is ``fdatasync``-ed at
most once every ``head_sync_s`` (and on close), not once per batch: a head
that lags only *under*-claims.  Why that is sound: the checkpoint is the
floor a truncation or rewrite is judged against, and every checkpoint ever
written names a genuine row of the chain.  After a power cut an older (still
genuine, MAC-verified) checkpoint may come back; every row it names is still
proven, and the rows after it (at most ``head_sync_s`` of appends, like a
crash between a commit and its checkpoint before) are counted and reported
as not covered, never passed off as proven.  A rollback of the database below
the checkpoint on disk is refused exactly as before.  The in-place write of
one 256-byte record sits inside one disk sector, so a power cut leaves the old
record or the new one; anything else reads as corrupt and refuses (fails
closed).  ``verify`` then proves: the chain links up to row N; the
checkpoint's MAC is genuine and row ``rows`` still has the checkpointed hash
(no truncation, no rewrite without the key); rows after the checkpoint (a
power cut within ``head_sync_s``, or rows appended by someone without the
key) are counted and reported as not covered.  It cannot prove anything against someone who holds
the key, nor against a rollback of the database *and* the head file together
to an older genuine pair (publish the head elsewhere for that).

**Refuse, never guess.**  Opening a file that is not an SQLite database, an
SQLite database that is not an audit trail, a database truncated or rewritten
since its checkpoint, a deleted checkpoint or key, or a damaged key raises
:class:`~antireplay.core.errors.AuditFileError`, which names the file and the
recovery (``antireplay audit verify PATH`` to see what is provable, then
``antireplay audit reanchor PATH`` to accept the current chain as the new
head, or moving the files aside to start a new trail).  Only an *empty* trail
is anchored automatically; a trail with rows and neither key nor checkpoint
(made before anchoring existed, or both files deleted) waits for an operator's
``antireplay audit reanchor PATH``.  A trail deleted while its checkpoint stays is
refused by name before any file is created (a refused start leaves nothing behind); a
running writer checks, before each group commit, that its path still names the file it
opened, so rows are never appended to a deleted (or replaced) trail where they would be
lost: those appends fail (``STATE_UNAVAILABLE``) instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import json
import logging
import os
import re
import secrets
import sqlite3
import tempfile
import threading
import time
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import AuditFileError, StateUnavailableError
from antireplay.state.durable import atomic_write, file_identity
from antireplay.state.groupcommit import GroupCommitter

log = logging.getLogger("antireplay.audit")

GENESIS = "0" * 64
_SAFE = re.compile(r"[A-Za-z0-9._:@/-]{1,64}")
_SCHEMA = """
CREATE TABLE IF NOT EXISTS audit (
    seq INTEGER PRIMARY KEY,
    at REAL NOT NULL,
    outcome TEXT NOT NULL,
    code TEXT,
    warning TEXT,
    msg_type INTEGER,
    sender TEXT,
    sender_verified INTEGER NOT NULL,
    msg_id TEXT,
    prev_hash TEXT NOT NULL,
    hash TEXT NOT NULL
);
"""
_FIELDS = (
    "seq",
    "at",
    "outcome",
    "code",
    "warning",
    "msg_type",
    "sender",
    "sender_verified",
    "msg_id",
)
_COLUMNS = ",".join(_FIELDS)  # constants only: no user input ever reaches SQL text
_TAIL = f"SELECT {_COLUMNS} FROM audit ORDER BY seq DESC LIMIT ?"  # noqa: S608
_ALL = f"SELECT {_COLUMNS}, prev_hash, hash FROM audit ORDER BY seq"  # noqa: S608
_EXPECTED_COLUMNS = [*_FIELDS, "prev_hash", "hash"]
_SQLITE_MAGIC = b"SQLite format 3\x00"
HEAD_FORMAT = "antireplay-audit-head"
HEAD_VERSION = 1
#: Bytes of one head record: well inside a 512-byte sector, so an in-place rewrite is atomic.
HEAD_RECORD = 256


def sanitize(value: object) -> str | None:
    """An identifier safe to store and print; anything suspicious becomes a short hash."""
    if value is None:
        return None
    text = value if isinstance(value, str) else repr(value)
    if _SAFE.fullmatch(text):
        return text
    return "sha256:" + hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()[:16]


def printable(value: object, limit: int = 200) -> str | None:
    """Free text (a STATE_LOST reason) safe to print: every character that is not printable
    (controls, escapes, bidi overrides) shown as its escape, at most ``limit`` characters."""
    if value is None:
        return None
    text = value if isinstance(value, str) else repr(value)
    shown = "".join(c if c.isprintable() else ascii(c)[1:-1] for c in text[: limit + 1])
    return shown if len(shown) <= limit else shown[: limit - 1] + "…"


#: Wall times antireplay can write: from the epoch to the end of year 9999.
LATEST_AT = 253_402_300_799.0


def valid_at(value: object) -> float | None:
    """The row's time if it is one antireplay could have written (a finite real within the
    years 1970-9999), else ``None`` (a tampered row: 1e300, NaN, a string)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    at = float(value)
    return at if 0.0 <= at <= LATEST_AT else None


def _wrongly_typed(row: dict[str, Any]) -> str | None:
    """The first column holding a value antireplay never writes, or ``None``."""
    for name, value in row.items():
        if name == "at":
            ok = valid_at(value) is not None
        elif name in ("seq", "sender_verified", "msg_type"):
            ok = (value is None and name == "msg_type") or (
                type(value) is int and (name != "sender_verified" or value in (0, 1))
            )
        else:
            ok = (value is None and name != "outcome") or isinstance(value, str)
        if not ok:
            return name
    return None


def _digest(prev: str, row: dict[str, Any]) -> str:
    body = json.dumps(row, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256((prev + body).encode()).hexdigest()


def _recovery(path: Path) -> str:
    return f"antireplay audit verify {path}, then antireplay audit reanchor {path}"


def _aside(path: Path) -> str:
    return (
        f"move {path} (and {path}.head) aside, keep them as evidence, and start a new trail; "
        "or give the path of an audit trail"
    )


@dataclass(frozen=True)
class Checkpoint:
    """A MAC-verified chain head read from the checkpoint file."""

    rows: int
    hash: str


class HeadAnchor:
    """The chain head, MACed with a key kept outside the database, checkpointed outside it."""

    def __init__(self, db: Path, key_path: Path | None = None, head_path: Path | None = None):
        self.db = db
        self.key_path = Path(key_path) if key_path else db.with_name(db.name + ".key")
        self.path = Path(head_path) if head_path else db.with_name(db.name + ".head")

    def _read(self, path: Path) -> bytes | None:
        """A file's bytes, ``None`` if it does not exist; anything else unreadable refuses."""
        try:
            return path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as exc:
            raise AuditFileError(
                str(path), f"unreadable ({exc.strerror})", recovery=_recovery(self.db)
            ) from None

    def load_key(self) -> bytes | None:
        """The head key, ``None`` if there is none yet; a damaged or exposed key refuses."""
        raw = self._read(self.key_path)
        if raw is None:
            return None
        if self.key_path.stat().st_mode & 0o077:
            raise AuditFileError(
                str(self.key_path), "readable by other users",
                recovery=f"chmod 600 {self.key_path}",
            )  # fmt: skip
        try:
            key = bytes.fromhex(raw.strip().decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            key = b""
        if len(key) != 32:
            raise AuditFileError(
                str(self.key_path), "not an audit head key (64 hex characters)",
                recovery=_recovery(self.db),
            )  # fmt: skip
        return key

    def create_key(self) -> bytes:
        """Make the key (0600) on first use: written whole to a temporary file, then linked
        into place, so nobody ever reads a half-written key; a concurrent creator's key wins."""
        key = secrets.token_bytes(32)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.key_path.name}.", dir=self.key_path.parent)
        try:
            with os.fdopen(fd, "wb") as handle:  # mkstemp files are 0600
                handle.write(key.hex().encode() + b"\n")
                handle.flush()
                os.fsync(handle.fileno())
            os.link(tmp, self.key_path)
        except FileExistsError:
            existing = self.load_key()
            assert existing is not None
            return existing
        finally:
            os.unlink(tmp)
        return key

    @staticmethod
    def mac(key: bytes, rows: int, head: str) -> str:
        return hmac.new(
            key, f"antireplay/v1 audit head|{rows}|{head}".encode(), "sha256"
        ).hexdigest()

    def record(self, key: bytes, rows: int, head: str) -> bytes:
        """The checkpoint as one fixed-size record (JSON padded with spaces, then a newline)."""
        body = {"format": HEAD_FORMAT, "version": HEAD_VERSION, "rows": rows, "hash": head,
                "mac": self.mac(key, rows, head)}  # fmt: skip
        return json.dumps(body, sort_keys=True).encode().ljust(HEAD_RECORD - 1) + b"\n"

    def write(self, key: bytes, rows: int, head: str, *, sync: bool = True) -> None:
        """Checkpoint the head: in place when the file already holds one record, so that
        ``sync=False`` costs no fsync yet survives a ``kill -9``; whole files (first
        write, an operator's edit) go through :func:`~antireplay.state.durable.atomic_write`."""
        record = self.record(key, rows, head)
        try:
            fd = os.open(self.path, os.O_WRONLY)
        except FileNotFoundError:
            fd = -1
        if fd >= 0:
            try:
                if os.fstat(fd).st_size == len(record):
                    os.pwrite(fd, record, 0)
                    if sync:
                        os.fdatasync(fd)
                    return
            finally:
                os.close(fd)
        # An older checkpoint after a power cut only under-claims (rows after it are reported),
        # so the directory fsync is skipped; the file's own fsync keeps it whole.
        atomic_write(self.path, record, sync_dir=False)

    def read(self, key: bytes | None) -> Checkpoint | None:
        """The checkpoint (``None`` if missing); a garbage or forged checkpoint refuses.

        Without a key the MAC cannot be checked and the checkpoint is returned unproven."""
        raw = self._read(self.path)
        if raw is None:
            return None
        try:
            body = json.loads(raw)
            ok = isinstance(body, dict) and body.get("format") == HEAD_FORMAT
            rows, head, mac = (body["rows"], body["hash"], body["mac"]) if ok else (0, "", "")
        except (ValueError, UnicodeDecodeError, KeyError):
            ok = False
        if not (ok and type(rows) is int and rows >= 0 and isinstance(head, str)
                and isinstance(mac, str)):  # fmt: skip
            raise AuditFileError(
                str(self.path), "not an audit head checkpoint (corrupt or truncated)",
                recovery=_recovery(self.db),
            )  # fmt: skip
        if key is not None and not hmac.compare_digest(mac, self.mac(key, rows, head)):
            raise AuditFileError(
                str(self.path), "head MAC does not verify (forged, or written with another key)",
                recovery=_recovery(self.db),
            )  # fmt: skip
        return Checkpoint(rows, head)


def _connect(path: Path, *, read_only: bool) -> sqlite3.Connection:
    """Open an audit trail, refusing anything that is not one (never creating a table in it)."""
    try:
        with path.open("rb") as handle:
            magic = handle.read(len(_SQLITE_MAGIC))
    except FileNotFoundError:
        magic = b""
        if read_only:
            raise AuditFileError(str(path), "does not exist", recovery=_aside(path)) from None
    except OSError as exc:
        raise AuditFileError(
            str(path), f"unreadable ({exc.strerror})", recovery=_aside(path)
        ) from None
    if magic and magic != _SQLITE_MAGIC:
        raise AuditFileError(str(path), "not an SQLite database", recovery=_aside(path))
    try:
        if read_only:
            db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, check_same_thread=False)
        else:
            db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
        try:
            tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            if "audit" in tables:
                columns = [r[1] for r in db.execute("PRAGMA table_info(audit)")]
                if columns != _EXPECTED_COLUMNS:
                    raise AuditFileError(
                        str(path), "has an audit table of another shape", recovery=_aside(path)
                    )
            elif tables or read_only:
                raise AuditFileError(
                    str(path), "is an SQLite database but not an audit trail",
                    recovery=_aside(path),
                )  # fmt: skip
            if not read_only:
                db.execute("PRAGMA journal_mode=WAL")
                db.execute("PRAGMA synchronous=FULL")
                db.executescript(_SCHEMA)
        except BaseException:
            db.close()
            raise
    except sqlite3.DatabaseError as exc:
        raise AuditFileError(
            str(path), f"not a usable SQLite database ({exc})", recovery=_aside(path)
        ) from None
    return db


def _last(db: sqlite3.Connection) -> tuple[int, str]:
    row = db.execute("SELECT seq, hash FROM audit ORDER BY seq DESC LIMIT 1").fetchone()
    return (0, GENESIS) if row is None else (int(row[0]), str(row[1]))


@dataclass(frozen=True)
class Record:
    """One audit row, as returned by :meth:`AuditLog.tail`."""

    seq: int
    at: float
    outcome: str
    code: str | None
    warning: str | None
    msg_type: int | None
    sender: str | None
    sender_verified: bool
    msg_id: str | None


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
        self._committer: GroupCommitter[dict[str, Any], int] = GroupCommitter(
            self._write_batch, name=f"antireplay-audit:{self.path.name}"
        )

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
        row: dict[str, Any] = {
            "at": at,
            "outcome": outcome,
            "code": code,
            "warning": warning,
            "msg_type": msg_type,
            "sender": sanitize(sender),
            "sender_verified": int(sender_verified),
            "msg_id": sanitize(msg_id),
        }
        if on_loop:
            return self._committer.enqueue_async(row)
        return self._committer.enqueue(row)

    def _write_batch(self, batch: Sequence[dict[str, Any]]) -> list[int]:
        """Chain and commit a group of rows in one write transaction; one head checkpoint."""
        with self._lock:
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
                for fields in batch:
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
            return list(range(first, seq + 1))

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
        """Write what is queued, make the head durable, then close."""
        self._committer.close()
        with self._lock:
            try:
                if self._head_dirty:
                    self.anchor.write(self._key, self._rows, self._head, sync=True)
                    self._head_dirty = False
            except OSError as exc:  # the head on disk may lag after a power cut: under-claims
                log.warning("audit head %s not made durable at close: %s", self.anchor.path, exc)
            finally:
                self._db.close()


def _records(rows: list[Any]) -> list[Record]:
    return [
        Record(r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7] == 1, r[8]) for r in reversed(rows)
    ]


def tail(path: str | Path, n: int = 20) -> list[Record]:
    """The newest ``n`` records, read-only: reading never writes a checkpoint or a key."""
    db = _connect(Path(path), read_only=True)
    try:
        return _records(db.execute(_TAIL, (n,)).fetchall())
    finally:
        db.close()


def shown(record: Record) -> dict[str, Any]:
    """One record as ``audit tail`` and the status page show it, whatever a trail edited
    behind our back holds: identifiers through ``sanitize`` again, the warning (a STATE_LOST
    reason is free text) through ``printable``, numbers only if they are numbers antireplay
    writes (else ``sanitize``d, and an impossible time is ``null`` / "invalid"), the time
    also as ISO 8601 UTC."""
    at = valid_at(record.at)
    return {
        "seq": record.seq if type(record.seq) is int else sanitize(record.seq),
        "at": at,
        "time": "invalid" if at is None else time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(at)),
        "outcome": sanitize(record.outcome),
        "code": sanitize(record.code),
        "warning": printable(record.warning),
        "msg_type": record.msg_type if type(record.msg_type) is int else sanitize(record.msg_type),
        "sender": sanitize(record.sender),
        "sender_verified": record.sender_verified,
        "msg_id": sanitize(record.msg_id),
    }


def _compare(db: sqlite3.Connection, checkpoint: Checkpoint) -> str | None:
    """Why the database disagrees with a genuine checkpoint, or ``None``."""
    if checkpoint.rows == 0:
        return None
    row = db.execute("SELECT hash FROM audit WHERE seq = ?", (checkpoint.rows,)).fetchone()
    if row is None:
        return f"truncated: the head checkpoint covers {checkpoint.rows} rows, they are gone"
    if row[0] != checkpoint.hash:
        return f"rewritten: row {checkpoint.rows} no longer has the checkpointed hash"
    return None


@dataclass(frozen=True)
class ChainReport:
    """Result of :func:`verify`: what the chain and the head checkpoint prove."""

    records: int
    broken_at: int | None
    reason: str | None
    #: "match", "missing" (no checkpoint), "no-key" (MAC not checkable), or the mismatch.
    head: str = "match"
    checkpoint_rows: int | None = None
    after_checkpoint: int = 0

    @property
    def chain_ok(self) -> bool:
        return self.broken_at is None

    @property
    def ok(self) -> bool:
        """The chain links and a genuine checkpoint matches it (no truncation, no rewrite)."""
        return self.broken_at is None and self.head == "match"

    def lines(self) -> list[str]:
        """What was proven and what was not, one fact per line."""
        out = [
            f"chain intact to row {self.records} ({self.records} records)"
            if self.chain_ok
            else f"chain broken at row {self.broken_at}: {self.reason}"
        ]
        if self.head == "match":
            out.append(f"head checkpoint matches row {self.checkpoint_rows} (MAC verified)")
            if self.after_checkpoint:
                out.append(
                    f"rows after the last checkpoint: {self.after_checkpoint} "
                    "(not covered by the head MAC: a crash before the checkpoint, or appended "
                    "without the key)"
                )
        elif self.head == "missing":
            out.append("head checkpoint missing: cannot prove the newest rows were not deleted")
        elif self.head == "no-key":
            out.append("head key missing: the checkpoint's MAC cannot be checked")
        else:
            out.append(f"head checkpoint does not match: {self.head}")
        return out


def verify(
    path: str | Path, *, head_key: str | Path | None = None, head_path: str | Path | None = None
) -> ChainReport:
    """Recompute the hash chain and check it against the head checkpoint (read-only).

    A file that is not an audit trail raises ``AuditFileError``; a missing, damaged or
    forged checkpoint or key is *reported* in ``head`` (the report says what is provable)."""
    path = Path(path)
    anchor = HeadAnchor(path, Path(head_key) if head_key else None,
                        Path(head_path) if head_path else None)  # fmt: skip
    db = _connect(path, read_only=True)
    try:
        chain = _walk(db)
        try:
            key = anchor.load_key()
            checkpoint = anchor.read(key)
        except AuditFileError as exc:
            return ChainReport(*chain, head=f"{exc.path}: {exc.problem}")
        if checkpoint is None:
            return ChainReport(*chain, head="missing")
        if key is None:
            return ChainReport(*chain, head="no-key", checkpoint_rows=checkpoint.rows)
        problem = _compare(db, checkpoint)
    except sqlite3.DatabaseError as exc:
        raise AuditFileError(
            str(path), f"unreadable audit trail ({exc})", recovery=_aside(path)
        ) from None
    finally:
        db.close()
    if problem is not None:
        return ChainReport(*chain, head=problem, checkpoint_rows=checkpoint.rows)
    after = max(0, chain[0] - checkpoint.rows)
    return ChainReport(*chain, checkpoint_rows=checkpoint.rows, after_checkpoint=after)


def _walk(db: sqlite3.Connection) -> tuple[int, int | None, str | None]:
    """(records, first broken row, reason) from recomputing every link."""
    prev, expected_seq, count = GENESIS, 1, 0
    for values in db.execute(_ALL):
        count += 1
        row = dict(zip(_FIELDS, values[:9], strict=True))
        wrong = _wrongly_typed(row)
        if wrong is not None:
            return count, expected_seq, f"invalid {wrong}: a value antireplay never writes"
        if row["seq"] != expected_seq:
            return count, expected_seq, "record missing or reordered"
        if values[9] != prev:
            return count, row["seq"], "prev_hash does not link"
        if values[10] != _digest(prev, row):
            return count, row["seq"], "record contents changed"
        prev, expected_seq = values[10], expected_seq + 1
    return count, None, None


def reanchor(
    path: str | Path, *, head_key: str | Path | None = None, head_path: str | Path | None = None
) -> ChainReport:
    """Accept the current, intact chain as the new head (after an operator checked it).

    Creates a new key when the old one is gone (a damaged or exposed key is replaced,
    never reused).  Refuses a broken chain."""
    path = Path(path)
    anchor = HeadAnchor(path, Path(head_key) if head_key else None,
                        Path(head_path) if head_path else None)  # fmt: skip
    try:
        key = anchor.load_key()
    except AuditFileError:
        key = None
        anchor.key_path.unlink()  # a damaged key is replaced, never reused
    key = key if key is not None else anchor.create_key()
    db = _connect(path, read_only=True)
    try:
        chain = _walk(db)
        if chain[1] is not None:
            raise AuditFileError(
                str(path), f"chain broken at row {chain[1]}: {chain[2]}; cannot re-anchor",
                recovery=_aside(path),
            )  # fmt: skip
        seq, head = _last(db)
    finally:
        db.close()
    anchor.write(key, seq, head)
    return ChainReport(*chain, checkpoint_rows=seq)
