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
* **Refuse, never reset.** Any problem raises
  :class:`~antireplay.errors.StateFileError`, which names the file and the
  recovery command, ``antireplay state repair PATH``.  Repair (:func:`repair`)
  salvages what it can and asks the owning module's *reseeder* for a value
  safely above anything that could have been used.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from antireplay.errors import StateFileError

FORMAT = "antireplay-state"
VERSION = 1

#: kind -> reseed(salvaged data or None, now_ns) -> safe new data.  Filled by owning modules.
Reseeder = Callable[[dict[str, Any] | None, int], dict[str, Any]]
REPAIRERS: dict[str, Reseeder] = {}


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


def atomic_write(path: Path, content: bytes) -> None:
    """Temp file + fsync + rename + directory fsync."""
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
    dir_fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


class DurableState:
    """A small JSON state file with checksum, generation and rollback witness."""

    def __init__(self, path: Path, *, kind: str) -> None:
        self.path = Path(path)
        self.witness = self.path.with_name(self.path.name + ".gen")
        self.kind = kind
        self.generation = 0
        self._lock = threading.Lock()
        self.writes = 0

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

    def load(self) -> dict[str, Any] | None:
        """The saved data, ``None`` for a fresh start, or StateFileError (never a silent reset)."""
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
        with self._lock:
            gen = self.generation + 1
            atomic_write(self.path, _seal(self.kind, gen, data))
            atomic_write(self.witness, _seal(self.kind, gen, {}))
            self.generation = gen
            self.writes += 1


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
    if kind not in REPAIRERS:
        raise ValueError(f"unknown state kind {kind!r}; known: {', '.join(sorted(REPAIRERS))}")
    gen, data = salvage(path)
    reseeded = REPAIRERS[kind](data, time.time_ns() if now_ns is None else now_ns)
    state = DurableState(path, kind=kind)
    state.generation = gen
    state.save(reseeded)
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
