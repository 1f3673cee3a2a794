"""The one crash-safe writer for small persisted state (counter leases, epochs, fences).

Theory of operation
-------------------
Replay protection that forgets its state on a crash re-opens every replay, and
one that silently resets a corrupt file to zero is worse.  So every small state
file in antireplay goes through :class:`DurableState`, and nobody else writes
state files.

* **Atomic replace.** A write goes to a temporary file in the same directory,
  is flushed and ``fsync``-ed, renamed over the old file with ``os.replace``,
  and the directory is ``fsync``-ed so the rename itself survives power loss.
  A reader sees the old state or the new one, never a mix.
* **Checksummed.** The file is one JSON object whose ``sha256`` field covers the
  canonical JSON of everything else (``format``, ``version``, ``kind``,
  ``generation``, ``data``).  Truncation or bit rot fails the check.
* **Monotonic generation, with a witness.** Each save increments
  ``generation`` and, after the main file, rewrites a small witness file
  (``<name>.gen``) with the same generation.  At load the main file must be at
  the witness's generation or one ahead (a crash between the two renames).  A
  main file behind its witness was rolled back (a restored backup, a copied
  image) and is refused.  Restoring *both* files together cannot be detected
  locally; epochs anchored to wall time (see :mod:`antireplay.epochs`) still
  bound the damage.
* **Witness records.**  :class:`Witness` is the other shape: one 64-byte checksummed
  record (deployment, generation, time) rewritten in place and ``fdatasync``-ed (or, for
  a SQLite store's witness, at most once a second: an older genuine record only
  under-claims), for writes too frequent for a rename (that witness, a state anchor).
* **Refuse, never reset.** Any problem raises
  :class:`~antireplay.core.errors.StateFileError`, which names the file and the
  recovery command, ``antireplay state repair PATH``.  That includes a file
  whose checksum is fine but whose content has the wrong shape (an owner
  parses it with :meth:`DurableState.load` and ``parse``; whatever the parser
  raises becomes the same typed error).  Repair (:func:`repair`) salvages what
  it can and asks the owning module's *reseeder* for a value safely above
  anything that could have been used.
* **One owner.** Two writers on one sender file hand out the same values, so an
  owner opens its file with ``exclusive=True``: an OS lock (``flock``) on
  ``PATH.lock`` is taken before the file is read and held for the owner's
  lifetime (until :meth:`DurableState.release` or garbage collection; the
  kernel drops it when the process dies, so ``kill -9`` never leaves a stale
  lock).  A second process, or a second object in the same process, is
  refused with a ``StateFileError`` saying the file is in use.  ``repair``
  takes the same lock, so a live file is never reseeded under its owner.  The
  lock file is never deleted (deleting it would let two owners lock two
  different inodes).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import struct
import tempfile
import threading
import time
import uuid
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final, Literal, TypeVar

from antireplay.core.errors import StateFileError

FORMAT = "antireplay-state"
VERSION = 1

#: kind -> reseed(salvaged data or None, now_ns) -> safe new data.  Filled by owning modules.
Reseeder = Callable[[dict[str, Any] | None, int], dict[str, Any]]
REPAIRERS: dict[str, Reseeder] = {}
T = TypeVar("T")


def register_repair(kind: str, reseed: Reseeder) -> None:
    """Let the module that owns a state kind say how to reseed it safely."""
    REPAIRERS[kind] = reseed


def _canonical(obj: dict[str, Any]) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()


def _seal(kind: str, generation: int, data: dict[str, Any]) -> bytes:
    body = {"format": FORMAT, "version": VERSION, "kind": kind, "generation": generation,
            "data": data}  # fmt: skip
    body["sha256"] = hashlib.sha256(_canonical(body)).hexdigest()
    return _canonical(body) + b"\n"


def atomic_write(path: Path, content: bytes, *, sync_dir: bool = True) -> None:
    """Temp file + fsync + rename + directory fsync.

    ``sync_dir=False`` skips the directory fsync, for files where losing the rename in a
    power cut (the old content comes back, complete) is safe, such as a head checkpoint."""
    directory = path.parent
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(content)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    if not sync_dir:
        return
    dir_fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def file_identity(path: Path) -> tuple[int, int] | None:
    """Which file ``path`` names now (device, inode), ``None`` if none: a writer that keeps
    its handle open compares this with what it opened, so a file deleted or replaced under
    it is noticed before it writes into a file nobody can open again."""
    try:
        found = os.stat(path)
    except FileNotFoundError:
        return None
    return found.st_dev, found.st_ino


def as_int(value: object, name: str) -> int:
    """A non-negative JSON integer (not a bool, not a string), else ``TypeError``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise TypeError(f"{name} must be a non-negative integer, got {value!r:.40}")
    return value


def as_hex(value: object, name: str, size: int) -> bytes:
    """``size`` bytes written as hex, else ``TypeError``."""
    if not isinstance(value, str) or len(value) != 2 * size:
        raise TypeError(f"{name} must be {2 * size} hex characters, got {value!r:.40}")
    try:
        return bytes.fromhex(value)
    except ValueError:
        raise TypeError(f"{name} must be {2 * size} hex characters, got {value!r:.40}") from None


class DurableState:
    """A small JSON state file with checksum, generation and rollback witness."""

    def __init__(self, path: Path, *, kind: str, exclusive: bool = False) -> None:
        self.path = Path(path)
        self.witness = self.path.with_name(self.path.name + ".gen")
        self.lockfile = self.path.with_name(self.path.name + ".lock")
        self.kind = kind
        self.exclusive = exclusive
        self.generation = 0
        self._lock = threading.Lock()
        self._held: weakref.finalize[Any, Any] | None = None
        self.writes = 0

    def acquire(self) -> None:
        """Take the owner lock on ``PATH.lock`` (non-blocking) or raise ``StateFileError``."""
        if self._held is not None and self._held.alive:
            return
        try:
            fd = os.open(self.lockfile, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        except OSError as exc:
            raise StateFileError(
                str(self.path), f"cannot open its lock file ({exc.strerror})"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise StateFileError(
                str(self.path),
                f"in use by another owner (lock {self.lockfile} is held)",
                recovery="stop the other process using this file; each sender needs its own",
            ) from None
        except OSError:
            os.close(fd)
            raise
        self._held = weakref.finalize(self, os.close, fd)

    def release(self) -> None:
        """Give the owner lock back (also done when this object is collected)."""
        if self._held is not None:
            self._held()

    def _read(self, path: Path) -> dict[str, Any]:
        """Parse and verify one file, or raise StateFileError."""
        try:
            raw = path.read_bytes()
        except OSError as exc:
            raise StateFileError(str(path), f"unreadable ({exc.strerror})") from None
        try:
            body = json.loads(raw)
        except (ValueError, UnicodeDecodeError):
            raise StateFileError(str(path), "corrupt or truncated (not valid JSON)") from None
        if not isinstance(body, dict) or body.get("format") != FORMAT:
            raise StateFileError(str(path), "not an antireplay state file")
        claimed = body.pop("sha256", None)
        if claimed != hashlib.sha256(_canonical(body)).hexdigest():
            raise StateFileError(str(path), "checksum mismatch (corrupt or edited)")
        if body.get("version") != VERSION:
            raise StateFileError(str(path), f"unsupported version {body.get('version')!r}")
        if body.get("kind") != self.kind:
            raise StateFileError(str(path), f"holds {body.get('kind')!r} state, not {self.kind!r}")
        gen = body.get("generation")
        if isinstance(gen, bool) or not isinstance(gen, int) or gen < 1:
            raise StateFileError(str(path), "invalid generation")
        if not isinstance(body.get("data"), dict):
            raise StateFileError(str(path), "invalid data")
        return body

    def load(self, parse: Callable[[dict[str, Any]], T] | None = None) -> Any:
        """The saved data (``parse``-d when given), ``None`` for a fresh start, or
        StateFileError (never a silent reset).  With ``exclusive`` the owner lock is
        taken first and given back if the file is refused."""
        if self.exclusive:
            self.acquire()
        try:
            data = self._load()
            if data is None or parse is None:
                return data
            try:
                return parse(data)
            except (TypeError, ValueError, KeyError) as exc:
                raise StateFileError(str(self.path), f"invalid content ({exc})") from None
        except BaseException:
            self.release()
            raise

    def _load(self) -> dict[str, Any] | None:
        with self._lock:
            has_main, has_witness = self.path.exists(), self.witness.exists()
            if not has_main and not has_witness:
                self.generation = 0
                return None
            if not has_main:
                raise StateFileError(str(self.path), "missing while its witness exists (deleted?)")
            body = self._read(self.path)
            gen = body["generation"]
            if has_witness:
                wgen = self._read(self.witness)["generation"]
                if gen < wgen:
                    raise StateFileError(
                        str(self.path), f"rolled back: generation {gen} < witness {wgen}"
                    )
                if gen > wgen + 1:
                    raise StateFileError(
                        str(self.path), f"witness rolled back: generation {gen} vs witness {wgen}"
                    )
            elif gen != 1:
                raise StateFileError(str(self.path), "witness missing; cannot rule out a rollback")
            self.generation = gen
            data: dict[str, Any] = body["data"]
            return data

    def save(self, data: dict[str, Any]) -> None:
        """Durably replace the state; returns only once it would survive a power cut."""
        if self.exclusive:
            self.acquire()
        with self._lock:
            gen = self.generation + 1
            atomic_write(self.path, _seal(self.kind, gen, data))
            atomic_write(self.witness, _seal(self.kind, gen, {}))
            self.generation = gen
            self.writes += 1


#: A SQLite store's witness file's magic (a state anchor file: the same layout, another).
WITNESS_MAGIC: Final = b"ARWITN02"


def seal_record(body: bytes, length: int = 64) -> bytes:
    """``body`` with the first 16 bytes of its SHA-256, padded to ``length`` (one sector)."""
    return (body + hashlib.sha256(body).digest()[:16]).ljust(length, b"\0")


def read_record(path: Path, size: int, least: int) -> bytes | Literal[False] | None:
    """The bytes of a record :func:`seal_record` wrote, its ``size``-byte body checked:
    ``None`` if absent, ``False`` if unreadable, shorter than ``least`` or torn."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError:
        return False
    if len(raw) < least or hashlib.sha256(raw[:size]).digest()[:16] != raw[size : size + 16]:
        return False
    return raw


class Witness:
    """The small file beside the database: deployment id, generation and the highest wall
    time of any commit, checksummed (a fence after a loss starts no lower than that, even
    if the wall clock stepped back across the restart).

    It is rewritten in place (one ``pwrite`` of 64 bytes, well inside one disk
    sector, then ``fdatasync`` unless the owner defers it); a torn or foreign file reads
    as ``None``.
    """

    MAGIC: Final = WITNESS_MAGIC
    _LAYOUT: Final = struct.Struct("<8s16sQd")

    def __init__(self, path: Path, magic: bytes = WITNESS_MAGIC) -> None:
        self.path = path
        self.magic = magic
        self._fd: int | None = None
        self._dirty = False

    def read(self) -> tuple[str, int, float] | bool | None:
        """``(deployment, generation, wall)``, ``None`` if absent, ``False`` if unreadable."""
        size = self._LAYOUT.size
        raw = read_record(self.path, size, size + 16)
        if not isinstance(raw, bytes):
            return raw
        magic, deployment, generation, wall = self._LAYOUT.unpack_from(raw)
        if magic != self.magic:
            return False
        return uuid.UUID(bytes=deployment).hex, generation, wall

    def write(self, deployment: str, generation: int, wall: float, *, sync: bool = True) -> None:
        """Rewrite the record; ``sync=False`` leaves it in the OS (a ``kill -9`` keeps it,
        a power cut may bring back an older one) until a later write syncs, or close."""
        body = self._LAYOUT.pack(self.magic, uuid.UUID(hex=deployment).bytes, generation, wall)
        record = seal_record(body)
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        os.pwrite(self._fd, record, 0)
        self._dirty = not sync
        if sync:
            os.fdatasync(self._fd)

    def close(self) -> None:
        if self._fd is not None:
            try:
                if self._dirty:
                    os.fdatasync(self._fd)
            finally:
                os.close(self._fd)
                self._fd = None
                self._dirty = False


def salvage(path: Path) -> tuple[int, dict[str, Any] | None]:
    """Best-effort read of a damaged state file: (highest generation seen, data or None)."""
    best_gen, data = 0, None
    for candidate in (path, path.with_name(path.name + ".gen")):
        try:
            body = json.loads(candidate.read_bytes())
        except (OSError, ValueError, UnicodeDecodeError):
            continue
        if not isinstance(body, dict):
            continue
        gen = body.get("generation")
        if isinstance(gen, int) and not isinstance(gen, bool):
            best_gen = max(best_gen, gen)
        if candidate == path and isinstance(body.get("data"), dict):
            data = body["data"]
    return best_gen, data


def repair(path: Path, kind: str, *, now_ns: int | None = None) -> dict[str, Any]:
    """Reseed a damaged state file safely above anything that could have been used."""
    if kind not in REPAIRERS:  # e.g. an "epoch-verifier" file: verifiers now use a store
        raise StateFileError(
            str(path),
            f"unknown state kind {kind!r}; known: {', '.join(sorted(REPAIRERS))}",
            recovery=f"move {path} aside",
        )
    state = DurableState(path, kind=kind, exclusive=True)
    state.acquire()  # never reseed a file under a live owner
    try:
        gen, data = salvage(path)
        reseeded = REPAIRERS[kind](data, time.time_ns() if now_ns is None else now_ns)
        state.generation = gen
        state.save(reseeded)
    finally:
        state.release()
    return reseeded


def read_kind(path: Path) -> str | None:
    """The kind recorded in a (possibly damaged) state file, if it can be read."""
    for candidate in (path, path.with_name(path.name + ".gen")):
        try:
            body = json.loads(candidate.read_bytes())
        except (OSError, ValueError, UnicodeDecodeError):
            continue
        if isinstance(body, dict) and isinstance(body.get("kind"), str):
            return str(body["kind"])
    return None
