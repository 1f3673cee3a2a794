"""The shared revocation list: which operator key ids no gateway on this state may trust.

Theory of operation
-------------------
The list lives beside the replay state, so every gateway sharing the state shares it:
a Redis set (and a hash of counters) under the store's hash tag for replicas, a small
SQLite database next to a ``sqlite:`` store's file for one host (``state.db`` ->
``state.revocations.db``, so ``rm state.db*`` does not un-revoke anything), a plain object
for the memory store (tests; one process).  A gateway never reads the list per request:
its watcher (:mod:`antireplay.wiring.keys`) polls :meth:`RevocationList.counters` (one
small read) every quarter second and reloads the set (:meth:`RevocationList.revoked`) only
when the ``revocations`` counter moved.  The ``reloads`` counter is ``antireplay keys
reload``: every gateway on the state re-reads its keys configuration when it moves.

Every method may raise :class:`~antireplay.core.errors.StateUnavailableError` (the store
is down); the watcher turns a long enough run of those into a fail-closed gateway.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
import threading
from pathlib import Path
from typing import Any, Protocol

import redis
import redis.cluster

from antireplay.core.errors import StateUnavailableError
from antireplay.state.spec import StoreSpec

#: The counters :meth:`RevocationList.counters` returns.
REVOCATIONS = "revocations"
RELOADS = "reloads"

#: SADD/SREM and bump the counter in one step (Redis runs a script atomically).
_CHANGE = """
local changed = redis.call(ARGV[1], KEYS[1], ARGV[2])
redis.call('HINCRBY', KEYS[2], ARGV[3], 1)
return changed
"""


class RevocationList(Protocol):
    """The revocation list of one state (see the module docstring)."""

    def counters(self) -> dict[str, int]: ...
    def revoked(self) -> frozenset[str]: ...
    def revoke(self, kid: str) -> bool: ...
    def unrevoke(self, kid: str) -> bool: ...
    def request_reload(self) -> None: ...
    def close(self) -> None: ...


class MemoryRevocations:
    """One process's list (the memory store's; tests share the object)."""

    def __init__(self) -> None:
        self._kids: set[str] = set()
        self._counters = {REVOCATIONS: 0, RELOADS: 0}
        self._lock = threading.Lock()

    def counters(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counters)

    def revoked(self) -> frozenset[str]:
        with self._lock:
            return frozenset(self._kids)

    def revoke(self, kid: str) -> bool:
        return self._change(kid, add=True)

    def unrevoke(self, kid: str) -> bool:
        return self._change(kid, add=False)

    def _change(self, kid: str, *, add: bool) -> bool:
        with self._lock:
            changed = (kid not in self._kids) if add else (kid in self._kids)
            (self._kids.add if add else self._kids.discard)(kid)
            self._counters[REVOCATIONS] += 1
            return changed

    def request_reload(self) -> None:
        with self._lock:
            self._counters[RELOADS] += 1

    def close(self) -> None:
        """Nothing to release."""


_SCHEMA = """
CREATE TABLE IF NOT EXISTS revoked (kid TEXT PRIMARY KEY) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS counters (name TEXT PRIMARY KEY, n INTEGER NOT NULL) WITHOUT ROWID;
INSERT OR IGNORE INTO counters VALUES ('revocations', 0), ('reloads', 0);
"""


def sqlite_path(state: str | Path) -> Path:
    """Where a ``sqlite:`` store's revocation list lives (next to it, not ``state.db*``)."""
    path = Path(state)
    return path.with_name(f"{path.stem}.revocations.db")


class SqliteRevocations:
    """The list of a ``sqlite:`` state (its own small database, WAL, one connection)."""

    def __init__(self, path: str | Path, timeout_s: float = 0.5) -> None:
        self.path = Path(path)
        self.timeout_s = timeout_s
        self._lock = threading.Lock()
        self._db: sqlite3.Connection | None = None

    def _open(self) -> sqlite3.Connection:
        """The connection, opened (and the schema made) on first use: a file that cannot be
        made yet (a full disk) is ``STATE_UNAVAILABLE`` now and tried again next time."""
        if self._db is None:
            with contextlib.suppress(OSError):  # 0600 (WAL/SHM take its mode); else connect says
                os.close(os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600))
            db = sqlite3.connect(
                self.path, timeout=self.timeout_s, isolation_level=None, check_same_thread=False
            )
            try:
                db.execute("PRAGMA journal_mode=WAL")
                db.execute("PRAGMA synchronous=FULL")
                db.executescript(_SCHEMA)
            except sqlite3.Error:
                db.close()
                raise
            self._db = db
        return self._db

    def _run(self, sql: str, *args: Any) -> list[tuple[Any, ...]]:
        try:
            with self._lock:
                return self._open().execute(sql, args).fetchall()
        except sqlite3.Error as exc:
            raise StateUnavailableError(f"revocation list {self.path}: {exc}") from None

    def counters(self) -> dict[str, int]:
        return {str(name): int(n) for name, n in self._run("SELECT name, n FROM counters")}

    def revoked(self) -> frozenset[str]:
        return frozenset(str(kid) for (kid,) in self._run("SELECT kid FROM revoked"))

    def revoke(self, kid: str) -> bool:
        return self._change("INSERT OR IGNORE INTO revoked VALUES (?)", kid)

    def unrevoke(self, kid: str) -> bool:
        return self._change("DELETE FROM revoked WHERE kid = ?", kid)

    def _change(self, sql: str, kid: str) -> bool:
        try:
            with self._lock:
                db = self._open()
                db.execute("BEGIN IMMEDIATE")
                try:
                    changed = db.execute(sql, (kid,)).rowcount > 0
                    db.execute("UPDATE counters SET n = n + 1 WHERE name = 'revocations'")
                except BaseException:
                    db.execute("ROLLBACK")
                    raise
                db.execute("COMMIT")
                return changed
        except sqlite3.Error as exc:
            raise StateUnavailableError(f"revocation list {self.path}: {exc}") from None

    def request_reload(self) -> None:
        self._run("UPDATE counters SET n = n + 1 WHERE name = 'reloads'")

    def close(self) -> None:
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None


class RedisRevocations:
    """The list of a Redis (or Redis Cluster) state: one set, one hash of counters."""

    def __init__(
        self, spec: StoreSpec, timeout_s: float = 0.5, prefix: str = "antireplay:"
    ) -> None:
        options: dict[str, Any] = {"socket_timeout": timeout_s, "socket_connect_timeout": timeout_s}
        self._redis: Any
        if spec.backend == "redis-cluster":
            self._redis = redis.cluster.RedisCluster.from_url(spec.target, **options)
        else:
            self._redis = redis.Redis.from_url(spec.target, **options)
        base = f"{prefix}{{antireplay}}:"  # the store's hash tag: one slot
        self._set, self._counters = f"{base}revoked", f"{base}key-counters"
        self._script = self._redis.register_script(_CHANGE)

    def _call(self, fn: Any, *args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except redis.RedisError as exc:
            raise StateUnavailableError(f"revocation list: {type(exc).__name__}: {exc}") from None

    def counters(self) -> dict[str, int]:
        raw = self._call(self._redis.hgetall, self._counters)
        found = {k.decode() if isinstance(k, bytes) else str(k): int(v) for k, v in raw.items()}
        return {REVOCATIONS: found.get(REVOCATIONS, 0), RELOADS: found.get(RELOADS, 0)}

    def revoked(self) -> frozenset[str]:
        members = self._call(self._redis.smembers, self._set)
        return frozenset(m.decode() if isinstance(m, bytes) else str(m) for m in members)

    def revoke(self, kid: str) -> bool:
        keys = [self._set, self._counters]
        return bool(self._call(self._script, keys=keys, args=["SADD", kid, REVOCATIONS]))

    def unrevoke(self, kid: str) -> bool:
        keys = [self._set, self._counters]
        return bool(self._call(self._script, keys=keys, args=["SREM", kid, REVOCATIONS]))

    def request_reload(self) -> None:
        self._call(self._redis.hincrby, self._counters, RELOADS, 1)

    def close(self) -> None:
        self._redis.close()


def open_revocations(spec: StoreSpec, memory: MemoryRevocations | None = None) -> RevocationList:
    """The revocation list of the state ``spec`` names (``memory``: the object a memory
    store's gateway and its tests share; a new one without it)."""
    if spec.backend == "sqlite":
        return SqliteRevocations(sqlite_path(spec.target))
    if spec.backend in ("redis", "redis-cluster"):
        return RedisRevocations(spec)
    return memory if memory is not None else MemoryRevocations()


__all__ = [
    "RELOADS",
    "REVOCATIONS",
    "MemoryRevocations",
    "RedisRevocations",
    "RevocationList",
    "SqliteRevocations",
    "open_revocations",
    "sqlite_path",
]
