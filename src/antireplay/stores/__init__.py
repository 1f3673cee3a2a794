"""Replay state stores: one small contract, three backends.

Theory of operation
-------------------
The policies (:mod:`antireplay.window`, counters, epochs) decide; a store only
keeps their state and offers the few **atomic** operations they need, so that
several threads, processes or gateway replicas sharing one store still accept
each message exactly once.  Stores hold no rules of their own.

The contract (:class:`ReplayStore`):

* ``lookup(key) -> expiry | None``: non-mutating; an entry at or past its
  expiry may still be returned, the caller compares with its clock.
* ``record(key, expires_at, now) -> bool``: atomically insert the key unless an
  entry that has not expired (``expiry >= now``) exists; True iff this call
  recorded it.  Two racers for one key: exactly one True.
* ``record_many(items, now) -> list[bool]``: the same for a batch (pipelined
  on Redis).
* ``advance(key, value) -> bool``: compare-and-advance for counters and epochs;
  sets ``value`` iff it is greater than the current one (or none exists).
* ``current(key) -> int | None``: non-mutating read of a counter.
* ``fence() -> float``: wall time before which the store may have forgotten
  accepted messages: a fresh ``MemoryStore`` returns its start time, a
  ``SqliteStore`` ``-inf``, a ``RedisStore`` the moment it found its state
  missing.  The window refuses anything stamped at or before ``fence + skew``
  (the **restart fence**), so a restart never opens a replay hole.

Backends: :class:`~antireplay.stores.memory.MemoryStore` (one process, the
default), :class:`~antireplay.stores.sqlite.SqliteStore` (one machine,
survives ``kill -9`` and reboots), :class:`~antireplay.stores.redis_store.RedisStore`
(many replicas; fails closed with ``STATE_UNAVAILABLE`` when Redis is down).
Select one from config with :func:`open_store`:
``memory``, ``sqlite:PATH`` or ``redis://HOST:PORT/DB``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

from antireplay.clock import Clock
from antireplay.errors import ConfigError


@runtime_checkable
class ReplayStore(Protocol):
    """Atomic replay state; see the module docstring for the contract."""

    def lookup(self, key: str) -> float | None: ...

    def record(self, key: str, expires_at: float, now: float) -> bool: ...

    def record_many(self, items: Sequence[tuple[str, float]], now: float) -> list[bool]: ...

    def advance(self, key: str, value: int) -> bool: ...

    def current(self, key: str) -> int | None: ...

    def fence(self) -> float: ...

    def close(self) -> None: ...


def open_store(spec: str, *, clock: Clock | None = None) -> ReplayStore:
    """Build a store from ``memory``, ``sqlite:PATH`` or ``redis://…`` (``rediss://`` too)."""
    if spec == "memory":
        from antireplay.stores.memory import MemoryStore  # noqa: PLC0415 - optional backends

        return MemoryStore(clock=clock)
    if spec.startswith("sqlite:") and len(spec) > len("sqlite:"):
        from antireplay.stores.sqlite import SqliteStore  # noqa: PLC0415

        return SqliteStore(spec[len("sqlite:") :])
    if spec.startswith(("redis://", "rediss://", "unix://")):
        from antireplay.stores.redis_store import RedisStore  # noqa: PLC0415

        return RedisStore(spec, clock=clock)
    raise ConfigError("store", spec, "memory, sqlite:PATH or redis://HOST:PORT/DB")


__all__ = ["ReplayStore", "open_store"]
