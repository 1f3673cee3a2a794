"""StateAnchor: what a restored copy of the state directory cannot reproduce, kept outside it.

Theory of operation
-------------------
A SQLite store detects a lost, replaced or rolled-back database from its witness, but
both live in one directory: a snapshot revert or a backup restore brings back a database
and witness that agree, and the replays accepted after the snapshot open again.  The
anchor is a third copy of ``(deployment, generation, time)`` somewhere the snapshot does
not reach: a file on another volume (``path``; the witness's 64-byte checksummed record,
rewritten in place and ``fdatasync``-ed), a Redis key (``redis``; durable as far as that
server's ``appendfsync`` goes), or both (read: the most advanced of the two).  The store
writes it inside its write transaction, before COMMIT, under SQLite's write lock (so
processes sharing the file write it in generation order); a failed write fails the
commit (``STATE_UNAVAILABLE``; a fresh ESTOP still passes).  At open
(:func:`~antireplay.state.sqlite.anchor_reason`, beside the witness rules) a database
behind its anchor, of another deployment, missing while the anchor exists, or with state
but no anchor (lost, or first use on an existing database) is a **loss**: the store's one
loss path raises the fence (no lower than the anchor's time), audits ``STATE_LOST`` and
counts it.  Removing the anchor with the directory is the documented reset.

**Written lazily, safely** (``every_s > 0``).  The record is then a lease: ``time`` is
"no commit happens after this without a newer anchor".  A commit at wall ``t`` writes
only once ``t`` is within ``every_s`` of the lease's end, extending it to ``t + 2 *
every_s`` (read first, never lowered: another process may hold a longer lease).  So at
most one write per ``every_s``.  A restored copy at least as new as the anchor's
generation may still miss commits made since the last write, but every one of those was
made at or before the lease's end ``U``, on a message stamped at or before ``U + skew``:
open raises the fence to ``U`` (the restart fence every memory store raises), which
refuses exactly those.  Nothing is open whose window a copy could claim; a restart
within ``skew + 2 * every_s`` of the last commit refuses in-flight commands that long.
With ``every_s == 0`` every commit writes the anchor and no restart fence is needed.
"""

from __future__ import annotations

import socket
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Literal

import redis

from antireplay.core.errors import StateUnavailableError
from antireplay.state.durable import Witness
from antireplay.state.spec import StoreSpec

#: The anchor file's magic (the witness's layout: deployment, generation, time, checksum).
ANCHOR_MAGIC: Final = b"ARANCH01"
#: The Redis anchor's key, followed by the host and the database's absolute path.
REDIS_KEY: Final = "antireplay:anchor:"


@dataclass(frozen=True)
class Anchored:
    """What an anchor vouches for: the deployment, its generation and the time (a lease
    end when written lazily, the last commit's time otherwise)."""

    deployment: str
    generation: int
    time: float


#: An anchor as read: the record, ``None`` if there is none yet, ``False`` if unreadable.
Read = Anchored | Literal[False] | None


class StateAnchor:
    """The anchor of one SQLite database: a file, a Redis key, or both (module docstring)."""

    def __init__(
        self, db: str | Path, *, path: str | Path | None = None, redis_url: str | None = None,
        every_s: float = 0.0, timeout_s: float = 2.0,
    ) -> None:  # fmt: skip
        if path is None and redis_url is None:
            raise ValueError("a state anchor needs a path, a Redis URL, or both")
        self.file = None if path is None else Witness(Path(path), ANCHOR_MAGIC)
        self.key = f"{REDIS_KEY}{socket.gethostname()}:{Path(db).resolve()}"
        self.redis_url = redis_url
        self._redis = None if redis_url is None else redis.Redis.from_url(
            redis_url, socket_timeout=timeout_s, socket_connect_timeout=timeout_s
        )  # fmt: skip
        self.every_s = every_s
        self.writes = 0
        self._until: float | None = None  # the lease end this process last read or wrote

    @property
    def lazy(self) -> bool:
        """Written at most every ``every_s``: open raises a restart fence to its time."""
        return self.every_s > 0

    def where(self) -> str:
        """Where the anchor lives, for the startup line and errors (no credentials)."""
        places = [] if self.file is None else [str(self.file.path)]
        if self.redis_url is not None:
            places.append(f"{StoreSpec.parse(self.redis_url).redacted()} key {self.key}")
        return " + ".join(places)

    def read(self) -> Read:
        """The most advanced record of the file and the Redis key; ``False`` if either is
        unreadable (a loss: fence), ``None`` if neither exists."""
        found: list[Anchored] = []
        for record in (self._read_file(), self._read_redis()):
            if record is False:
                return False
            if isinstance(record, Anchored):
                found.append(record)
        if not found:
            return None
        best = max(found, key=lambda a: (a.generation, a.time))
        return Anchored(best.deployment, best.generation, max(a.time for a in found))

    def _read_file(self) -> Read:
        if self.file is None:
            return None
        got = self.file.read()
        if got is None or got is False:
            return got
        assert isinstance(got, tuple)
        return Anchored(*got)

    def _read_redis(self) -> Read:
        if self._redis is None:
            return None
        try:
            raw = self._redis.get(self.key)
        except redis.RedisError as exc:
            raise StateUnavailableError(f"state anchor {self.where()}: {exc}") from None
        if raw is None:
            return None
        try:
            text = raw.decode("ascii") if isinstance(raw, bytes) else str(raw)
            deployment, generation, when = text.split(" ")
            return Anchored(uuid.UUID(hex=deployment).hex, int(generation), float(when))
        except (UnicodeDecodeError, ValueError):
            return False

    def advance(self, deployment: str, generation: int, wall: float) -> None:
        """Called inside the store's write transaction, before COMMIT: vouch for
        ``generation`` (now, or lazily while the lease covers ``wall``)."""
        if not self.lazy:
            self._write(Anchored(deployment, generation, wall))
            return
        if self._until is not None and wall <= self._until - self.every_s:
            return  # the lease in place still covers this commit
        held = self.read()
        until = wall + 2 * self.every_s
        if isinstance(held, Anchored):
            until = max(until, held.time)  # never shorten another process's lease
        self._write(Anchored(deployment, generation, until))

    def _write(self, record: Anchored) -> None:
        try:
            if self.file is not None:
                self.file.write(record.deployment, record.generation, record.time)
            if self._redis is not None:
                value = f"{record.deployment} {record.generation} {record.time!r}"
                self._redis.set(self.key, value)
        except (OSError, redis.RedisError) as exc:
            self._until = None  # unknown now: the next commit writes again
            raise StateUnavailableError(f"state anchor {self.where()}: {exc}") from None
        self._until = record.time
        self.writes += 1

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
        if self._redis is not None:
            self._redis.close()
