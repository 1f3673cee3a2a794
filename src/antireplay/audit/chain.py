"""The audit trail's format: the schema, the hash chain, the head anchor, the sanitizer.

Each row stores ``hash = SHA-256(prev_hash | canonical JSON of the row)``; the first
row chains from :data:`GENESIS`, or, in a later segment of the trail, from the last
hash of the segment before it, which the segment's one ``segment`` row records (its
:class:`Link`, MACed with the head key).  A file without that row is segment 1.  The
head ``(rows, last hash, oldest segment kept)`` is MACed with a key kept outside the
database and checkpointed to a file beside it (:class:`HeadAnchor`); the key is a file's
32 bytes, or a key kept in a token that computes the HMAC itself (:class:`MacKey`).
The writer (:mod:`.writer`), the reader (:mod:`.reader`) and the verifier
(:mod:`.verifier`) share these definitions and nothing else.  A row to write is one
:class:`AuditRow`, whichever adapter builds it; a row read back is a :class:`Record`, the
same fields and its ``seq``.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import re
import secrets
import sqlite3
import tempfile
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Protocol, TypeAlias

from antireplay.core.errors import AuditFileError
from antireplay.state.durable import atomic_write

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
CREATE TABLE IF NOT EXISTS segment (
    n INTEGER PRIMARY KEY,
    first_seq INTEGER NOT NULL,
    prev_hash TEXT NOT NULL,
    mac TEXT NOT NULL
);
"""


@dataclass(frozen=True, slots=True)
class AuditRow:
    """One row to write: every adapter builds this value and hands it to the writer, which
    sanitizes ``sender`` and ``msg_id`` and chains it.  Its fields are the trail's columns
    (after ``seq``) and the keys of the row the hash covers."""

    at: float
    outcome: str
    code: str | None = None
    warning: str | None = None
    msg_type: int | None = None
    sender: str | None = None
    sender_verified: bool = False
    msg_id: str | None = None


@dataclass(frozen=True, slots=True, kw_only=True)
class Record(AuditRow):
    """One row read back (:meth:`AuditLog.tail`): the row as stored, and its ``seq``."""

    seq: int


#: The row's fields, spelled once (:class:`AuditRow`); a stored row leads with ``seq``.
ROW_FIELDS = tuple(f.name for f in fields(AuditRow))
_FIELDS = ("seq", *ROW_FIELDS)
_COLUMNS = ",".join(_FIELDS)  # constants only: no user input ever reaches SQL text
_TAIL = f"SELECT {_COLUMNS} FROM audit ORDER BY seq DESC LIMIT ?"  # noqa: S608
_ALL = f"SELECT {_COLUMNS}, prev_hash, hash FROM audit ORDER BY seq"  # noqa: S608
_EXPECTED_COLUMNS = [*_FIELDS, "prev_hash", "hash"]
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


class MacKey(Protocol):
    """A head key that never leaves its token: HMAC-SHA256 computed there
    (:class:`antireplay.keys.pkcs11.TokenMac`); a failing token raises ``OSError``."""

    def mac(self, data: bytes, /) -> bytes: ...


#: The head key: a key file's 32 bytes, or a key in a token.
HeadKey: TypeAlias = "bytes | MacKey"


def hexmac(key: HeadKey, message: bytes) -> str:
    """HMAC-SHA256 of ``message`` under the head key, in hex."""
    if isinstance(key, bytes):
        return hmac.new(key, message, "sha256").hexdigest()
    return key.mac(message).hex()


def spill_key(key: HeadKey) -> bytes:
    """The ESTOP spill's MAC key: the head key itself, or for a key in a token one derived
    from it at open, so ESTOP rows are still spilled (and verified at the next open) after
    the token has failed."""
    return key if isinstance(key, bytes) else key.mac(b"antireplay/v1 audit spill key")


@dataclass(frozen=True)
class Checkpoint:
    """A MAC-verified chain head read from the checkpoint file."""

    rows: int
    hash: str
    #: The oldest segment retention keeps: older ones were removed by retention, on purpose.
    first: int = 1


@dataclass(frozen=True)
class Link:
    """Where a segment starts: its number, its first row and the hash that row chains from."""

    n: int
    first: int
    prev: str
    mac: str = ""

    def message(self) -> bytes:
        return f"antireplay/v1 audit segment|{self.n}|{self.first}|{self.prev}".encode()


#: Segment 1 of every trail (and the whole of a trail written before segments existed).
FIRST_LINK = Link(1, 1, GENESIS)


class HeadAnchor:
    """The chain head, MACed with a key kept outside the database, checkpointed outside it."""

    def __init__(
        self, db: Path, key_path: str | Path | MacKey | None = None,
        head_path: str | Path | None = None,
    ) -> None:  # fmt: skip
        self.db = db
        #: A key in a token, instead of the key file.
        self.token = None if key_path is None or isinstance(key_path, (str, Path)) else key_path
        named = isinstance(key_path, (str, Path)) and str(key_path)
        self.key_path = Path(key_path) if named else db.with_name(db.name + ".key")  # type: ignore[arg-type]
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

    def load_key(self) -> HeadKey | None:
        """The head key, ``None`` if there is none yet; a damaged or exposed key refuses."""
        if self.token is not None:
            return self.token
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

    def create_key(self) -> HeadKey:
        """Make the key (0600) on first use: written whole to a temporary file, then linked
        into place, so nobody ever reads a half-written key; a concurrent creator's key wins.
        A key in a token is made by its operator, never here."""
        if self.token is not None:
            return self.token
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
    def mac(key: HeadKey, rows: int, head: str, first: int = 1) -> str:
        """The head's MAC; version 1 (``first == 1``, nothing removed) keeps its old message."""
        text = f"antireplay/v1 audit head|{rows}|{head}" + (f"|first {first}" if first > 1 else "")
        return hexmac(key, text.encode())

    @classmethod
    def mac_ok(cls, key: HeadKey, head: Checkpoint, mac: str) -> bool:
        """Whether ``mac`` is ``head``'s MAC under ``key``."""
        return hmac.compare_digest(mac, cls.mac(key, head.rows, head.hash, head.first))

    @staticmethod
    def link(key: HeadKey, n: int, first: int, prev: str) -> Link:
        """A segment's start, MACed: proof that the writer, not a deleter, cut the chain there."""
        return Link(n, first, prev, hexmac(key, Link(n, first, prev).message()))

    @staticmethod
    def link_ok(key: HeadKey, link: Link) -> bool:
        if link == FIRST_LINK:
            return True  # segment 1 starts from GENESIS: nothing to prove
        expected = hexmac(key, link.message())
        return hmac.compare_digest(link.mac, expected)

    def record(self, key: HeadKey, rows: int, head: str, first: int = 1) -> bytes:
        """The checkpoint as one fixed-size record (JSON padded with spaces, then a newline);
        version 2 adds the oldest segment kept, once retention has removed one."""
        body: dict[str, Any] = {"format": HEAD_FORMAT, "version": HEAD_VERSION, "rows": rows,
                                "hash": head, "mac": self.mac(key, rows, head, first)}  # fmt: skip
        if first > 1:
            body.update(version=2, first=first)
        return json.dumps(body, sort_keys=True).encode().ljust(HEAD_RECORD - 1) + b"\n"

    def write(
        self, key: HeadKey, rows: int, head: str, *, sync: bool = True, first: int = 1
    ) -> None:
        """Checkpoint the head: in place when the file already holds one record, so that
        ``sync=False`` costs no fsync yet survives a ``kill -9``; whole files (first
        write, an operator's edit) go through :func:`~antireplay.state.durable.atomic_write`."""
        record = self.record(key, rows, head, first)
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

    def read(self, key: HeadKey | None) -> Checkpoint | None:
        """The checkpoint (``None`` if missing); a garbage or forged checkpoint refuses.

        Without a key the MAC cannot be checked and the checkpoint is returned unproven."""
        raw = self._read(self.path)
        if raw is None:
            return None
        try:
            body = json.loads(raw)
            ok = isinstance(body, dict) and body.get("format") == HEAD_FORMAT
            rows, head, mac = (body["rows"], body["hash"], body["mac"]) if ok else (0, "", "")
            first = body.get("first", 1) if ok else 1
        except (ValueError, UnicodeDecodeError, KeyError):
            ok = False
        if not (ok and type(rows) is int and rows >= 0 and isinstance(head, str)
                and isinstance(mac, str) and type(first) is int and first >= 1):  # fmt: skip
            raise AuditFileError(
                str(self.path), "not an audit head checkpoint (corrupt or truncated)",
                recovery=_recovery(self.db),
            )  # fmt: skip
        if key is not None and not hmac.compare_digest(mac, self.mac(key, rows, head, first)):
            raise AuditFileError(
                str(self.path), "head MAC does not verify (forged, or written with another key)",
                recovery=_recovery(self.db),
            )  # fmt: skip
        return Checkpoint(rows, head, first)


def _connect(path: Path, *, read_only: bool) -> sqlite3.Connection:
    """Open an audit trail, refusing anything that is not one (never creating a table in it).

    The file is only ever opened through SQLite: closing any other descriptor of it would
    drop the POSIX locks this process's writer holds, and another process closing its last
    connection would then delete the WAL under that writer."""
    if read_only and not path.exists():
        raise AuditFileError(str(path), "does not exist", recovery=_aside(path))
    if path.is_dir() or (path.exists() and not os.access(path, os.R_OK)):
        raise AuditFileError(str(path), "unreadable (not a readable file)", recovery=_aside(path))
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
        problem = (
            "not an SQLite database"
            if str(exc) == "file is not a database"
            else f"not a usable SQLite database ({exc})"
        )
        raise AuditFileError(str(path), problem, recovery=_aside(path)) from None
    return db


def _link(db: sqlite3.Connection) -> Link:
    """Where this segment starts (:data:`FIRST_LINK` for a file without a ``segment`` row);
    a wrongly typed or doubled row refuses, as any value antireplay never writes."""
    try:
        rows = db.execute("SELECT n, first_seq, prev_hash, mac FROM segment").fetchall()
    except sqlite3.OperationalError:  # no such table: a trail written before segments
        return FIRST_LINK
    if not rows:
        return FIRST_LINK
    n, first, prev, mac = rows[0]
    if len(rows) > 1 or not (type(n) is int and type(first) is int and n >= 1 and first >= 1
                             and isinstance(prev, str) and isinstance(mac, str)):  # fmt: skip
        raise sqlite3.DatabaseError("its segment row is not one antireplay writes")
    return Link(n, first, prev, mac)


def _last(db: sqlite3.Connection) -> tuple[int, str]:
    """The segment's last (seq, hash); an empty segment ends where its link starts it."""
    row = db.execute("SELECT seq, hash FROM audit ORDER BY seq DESC LIMIT 1").fetchone()
    if row is not None:
        return int(row[0]), str(row[1])
    link = _link(db)
    return link.first - 1, link.prev


def _records(rows: list[Any]) -> list[Record]:
    return [
        Record(r[1], r[2], r[3], r[4], r[5], r[6], r[7] == 1, r[8], seq=r[0])
        for r in reversed(rows)
    ]


def _compare(db: sqlite3.Connection, checkpoint: Checkpoint) -> str | None:
    """Why the database disagrees with a genuine checkpoint, or ``None``."""
    if checkpoint.rows == 0:
        return None
    row = db.execute("SELECT hash FROM audit WHERE seq = ?", (checkpoint.rows,)).fetchone()
    link = _link(db)
    if row is None and checkpoint.rows == link.first - 1:
        row = (link.prev,)  # the head is the previous segment's last row: this one starts there
    if row is None:
        return f"truncated: the head checkpoint covers {checkpoint.rows} rows, they are gone"
    if row[0] != checkpoint.hash:
        return f"rewritten: row {checkpoint.rows} no longer has the checkpointed hash"
    return None
