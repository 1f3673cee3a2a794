"""StateAnchor: what a restored copy of the state directory cannot reproduce, kept outside it.

Theory of operation
-------------------
A SQLite store detects a lost, replaced or rolled-back database from its witness, but
both live in one directory: a snapshot revert or a backup restore brings back a database
and witness that agree.  The anchor is another copy of ``(deployment, generation, time)``
where the snapshot does not reach: a file on another volume (``path``; 64 checksummed
bytes rewritten in place and ``fdatasync``-ed, then the state's path as text), a Redis key
(``redis``), or both.  **Each copy is checked on its own** (:meth:`StateAnchor.read`): any
one missing, unreadable or behind is a loss, so a flushed Redis is not hidden by the file.
The store writes every copy inside its write transaction, before COMMIT; a failed write
fails the commit (``STATE_UNAVAILABLE``; a fresh ESTOP still passes), and an anchor that
cannot be reached at open leaves the store unverified and unready until it can.

**One anchor, one state.**  The file records a digest of the database's resolved path
(and the path, for errors).  A file written for another path, of another deployment, is
another state's: refused (``StateFileError`` naming both and the recovery), never adopted
(two gateways on one ``path`` would otherwise hand it back and forth, and a restore of
either would go unseen).  Processes sharing one database agree on its deployment, so
they share the file whatever path they mount it at.  The Redis record is keyed by the
deployment (``antireplay:anchor:DEPLOYMENT``: every sharer, on any host, writes the same
key; a new hostname is no loss); ``antireplay:anchor-at:HOST:PATH`` names the deployment
last opened there, so a database deleted with its witness is still found behind its
anchor.  Redis writes run one script that never lowers the generation or the time.

**Lazy** (``every_s > 0``): the record is a lease, "no commit after ``time`` without a
newer anchor"; a commit writes only once within ``every_s`` of the lease's end, extending
it to ``t + 2 * every_s``.  Open raises the fence to the lease's end (refusing what a copy
as new as the anchor may have missed) and says so like any fence (log, metric, audit).
"""

from __future__ import annotations

import hashlib
import os
import socket
import stat
import struct
import uuid
from pathlib import Path
from typing import Final

import redis

from antireplay.core.errors import ConfigError, StateFileError, StateUnavailableError
from antireplay.state.durable import read_record, seal_record
from antireplay.state.loss import Anchored, Read
from antireplay.state.spec import StoreSpec

#: ``Anchored`` and ``Read`` stay importable from here (they live in :mod:`.loss`).
__all__ = ["AnchorUnavailableError", "Anchored", "Read", "StateAnchor", "check_anchor_path"]

#: The anchor file's magic (``ARANCH01``: the previous layout, still recognised as ours).
ANCHOR_MAGIC: Final = b"ARANCH02"
_OLD_MAGIC: Final = b"ARANCH01"
#: The Redis record's key prefix, followed by the deployment id.
REDIS_KEY: Final = "antireplay:anchor:"
#: The Redis key naming the deployment last opened at ``HOST:PATH``.
REDIS_AT: Final = "antireplay:anchor-at:"
_LAYOUT: Final = struct.Struct("<8s16sQd8s")  # magic, deployment, generation, time, state
_RECORD: Final = 64
#: Lua: raise the record to (generation, time) without ever lowering either; name it.
_WRITE = """
local held = redis.call('GET', KEYS[1])
local gen, t = tonumber(ARGV[2]), tonumber(ARGV[3])
if held then
  local g0, t0 = string.match(held, '^%x+ (%d+) (%S+)$')
  if g0 then gen = math.max(gen, tonumber(g0)); t = math.max(t, tonumber(t0)) end
end
redis.call('SET', KEYS[1], ARGV[1] .. ' ' .. string.format('%d', gen) .. ' ' ..
           string.format('%.17g', t))
redis.call('SET', KEYS[2], ARGV[1])
return 1
"""


class AnchorUnavailableError(StateUnavailableError):
    """The anchor cannot be reached: the store stays unverified (and unready) until it can."""


def state_digest(db: str | Path) -> bytes:
    """What names one state in the anchor file: its database's resolved path, hashed."""
    return hashlib.sha256(str(Path(db).resolve()).encode()).digest()[:8]


def check_anchor_path(path: Path, avoid: dict[str, Path]) -> None:
    """Refuse (``ConfigError``) an anchor path that writing would damage or that a snapshot
    of the state restores with it: another antireplay file, inside the state's directory, a
    directory, a device or pseudo-file, or an existing file that is not an anchor."""

    def refuse(why: str) -> ConfigError:
        return ConfigError("state.anchor.path", str(path), f"a file of its own ({why})")

    resolved = path.resolve()
    for name, other in avoid.items():
        if resolved == other.resolve():
            raise refuse(f"this is the {name}")
    state_dir = avoid["state database"].resolve().parent
    if state_dir in (resolved, *resolved.parents):
        raise refuse(f"inside the state directory {state_dir}: a snapshot restores both")
    if str(resolved).startswith(("/proc/", "/sys/", "/dev/")):
        raise refuse("not on a real filesystem")
    if not resolved.parent.is_dir():
        raise ConfigError("state.anchor.path", str(path), "a file in an existing directory")
    try:
        mode = resolved.stat().st_mode
    except FileNotFoundError:
        return
    if not stat.S_ISREG(mode):
        raise refuse("this is not a regular file")
    with resolved.open("rb") as fh:
        head = fh.read(8)
    if head and head not in (ANCHOR_MAGIC, _OLD_MAGIC):
        raise refuse("this file exists and is not a state anchor; it is left untouched")


class StateAnchor:
    """The anchor of one SQLite database: a file, a Redis key, or both (module docstring)."""

    def __init__(
        self, db: str | Path, *, path: str | Path | None = None, redis_url: str | None = None,
        every_s: float = 0.0, timeout_s: float = 2.0,
    ) -> None:  # fmt: skip
        if path is None and redis_url is None:
            raise ValueError("a state anchor needs a path, a Redis URL, or both")
        self.db = str(Path(db).resolve())
        self.state = state_digest(db)
        self.path = None if path is None else Path(path)
        self.at_key = f"{REDIS_AT}{socket.gethostname()}:{self.db}"
        self.redis_url = redis_url
        self._redis = None if redis_url is None else redis.Redis.from_url(
            redis_url, socket_timeout=timeout_s, socket_connect_timeout=timeout_s
        )  # fmt: skip
        self._script = None if self._redis is None else self._redis.register_script(_WRITE)
        self.every_s = every_s
        self.writes = 0
        self._fd: int | None = None
        self._named = False  # this process wrote its state's path into the file
        self._until: float | None = None  # the lease end this process last read or wrote

    @property
    def lazy(self) -> bool:
        """Written at most every ``every_s``: open raises a restart fence to its time."""
        return self.every_s > 0

    def where(self) -> str:
        """Where the anchor lives, for the startup line and errors (no credentials)."""
        places = [] if self.path is None else [str(self.path)]
        if self.redis_url is not None:
            places.append(f"{StoreSpec.parse(self.redis_url).redacted()}")
        return " + ".join(places)

    def key(self, deployment: str) -> str:
        """The Redis record of ``deployment``."""
        return f"{REDIS_KEY}{deployment}"

    def read(self, deployment: str | None) -> dict[str, Read]:
        """Each configured copy (``where`` -> record) for the state of ``deployment`` (the
        database's or its witness's; ``None``: neither exists).  A file written for
        another state raises ``StateFileError``; an unreachable Redis,
        ``StateUnavailableError``."""
        copies: dict[str, Read] = {}
        if self.path is not None:
            copies[str(self.path)] = self._read_file(deployment)
        if self._redis is not None:
            where = StoreSpec.parse(self.redis_url or "").redacted()
            copies[where] = self._read_redis(deployment)
        return copies

    def _read_file(self, deployment: str | None) -> Read:
        assert self.path is not None
        raw = read_record(self.path, _LAYOUT.size, _RECORD)
        if not isinstance(raw, bytes):
            return raw
        magic, dep, generation, when, state = _LAYOUT.unpack_from(raw)
        if magic != ANCHOR_MAGIC:
            return False
        record = Anchored(uuid.UUID(bytes=dep).hex, generation, when)
        if state != self.state and record.deployment != deployment:
            owner = raw[_RECORD:].decode("utf-8", "replace") or "another state"
            raise StateFileError(
                str(self.path),
                f"this state anchor belongs to {owner} (deployment {record.deployment}), "
                f"not to {self.db}",
                recovery=(
                    "give each state its own state.anchor.path; if that state moved here, "
                    f"mv {self.path} {self.path}.old (the next start fences)"
                ),
            )
        return record

    def _read_redis(self, deployment: str | None) -> Read:
        assert self._redis is not None
        try:
            if deployment is None:
                named = self._redis.get(self.at_key)
                if named is None:
                    return None
                deployment = named.decode("ascii", "replace") if isinstance(named, bytes) else named
            raw = self._redis.get(self.key(deployment))
        except redis.RedisError as exc:
            raise AnchorUnavailableError(f"state anchor {self.where()}: {exc}") from None
        if raw is None:
            return None
        try:
            text = raw.decode("ascii") if isinstance(raw, bytes) else str(raw)
            dep, generation, when = text.split(" ")
            return Anchored(uuid.UUID(hex=dep).hex, int(generation), float(when))
        except (UnicodeDecodeError, ValueError):
            return False

    def ping(self) -> None:
        """``StateUnavailableError`` unless every copy can be reached (records nothing)."""
        if self._redis is not None:
            try:
                self._redis.ping()
            except redis.RedisError as exc:
                raise AnchorUnavailableError(f"state anchor {self.where()}: {exc}") from None

    def advance(self, deployment: str, generation: int, wall: float) -> None:
        """Called inside the store's write transaction, before COMMIT: vouch for
        ``generation`` (now, or lazily while the lease covers ``wall``)."""
        if not self.lazy:
            self._write(Anchored(deployment, generation, wall))
            return
        if self._until is not None and wall <= self._until - self.every_s:
            return  # the lease in place still covers this commit
        until = wall + 2 * self.every_s
        held = None if self.path is None else self._read_file(deployment)
        if isinstance(held, Anchored):  # never shorten a sharer's lease (Redis: the script)
            until = max(until, held.time)
        self._write(Anchored(deployment, generation, until))

    def _write(self, record: Anchored) -> None:
        try:
            if self.path is not None:
                self._write_file(record)
            if self._script is not None:
                self._script(
                    keys=[self.key(record.deployment), self.at_key],
                    args=[record.deployment, record.generation, repr(record.time)],
                )
        except (OSError, redis.RedisError) as exc:
            self._until = None  # unknown now: the next commit writes again
            raise AnchorUnavailableError(f"state anchor {self.where()}: {exc}") from None
        self._until = record.time
        self.writes += 1

    def _write_file(self, record: Anchored) -> None:
        assert self.path is not None
        body = _LAYOUT.pack(ANCHOR_MAGIC, uuid.UUID(hex=record.deployment).bytes,
                            record.generation, record.time, self.state)  # fmt: skip
        data = seal_record(body, _RECORD)
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        if not self._named:  # the path, for the error another state's open gives
            data += self.db.encode()
            os.ftruncate(self._fd, len(data))
        os.pwrite(self._fd, data, 0)
        os.fdatasync(self._fd)
        self._named = True

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        if self._redis is not None:
            self._redis.close()
