"""Replay state stores: one contract that carries the safety, three backends that keep it.

Theory of operation
-------------------
The policies decide; a store keeps their state and offers the few **atomic**
operations they need, so threads, processes or replicas sharing one store accept
each message exactly once (:class:`ReplayStore`):

* ``lookup(key) -> Seen``: records nothing (the pipeline's pre-crypto check).
* ``commit(key, expires_at, now, force) -> Seen``: atomically record ``key``
  unless it has a live entry (``expiry >= now``); ``force`` (a fresh ESTOP)
  extends a live entry instead.  Two racers for one key: exactly one gets
  ``recorded``.  Data-loss detection runs *in the same atomic operation*.
  ``commit_async`` is the same commit for an event loop: a group-committing store
  awaits its batch holding no thread, the others run ``commit`` through the
  caller's ``offload`` (:func:`offloaded`).
* ``advance(key, value) -> bool`` / ``current(key)``: compare-and-advance for
  high-water counters (MAVLink stream state), with the same loss detection.
* ``verify() -> Seen``: run the loss detection now (start-up; a MAVLink guard
  taking its lease), returning the fence and watermark.
* ``status()``: figures for ``/metrics`` (entries, watermark, fence,
  evictions, data-loss events).
* ``StoreSpec.parse`` (:mod:`antireplay.state.spec`) is the one grammar of store specs.
* ``ready()``: the one readiness probe: raise ``STATE_UNAVAILABLE`` unless a commit could go through
  now (``/readyz``); records nothing, so it never notices a loss in place of
  the commit that fences and audits it.

Every :class:`~antireplay.core.window.Seen` carries the **watermark** (an entry
removed before its expiry raises it to that expiry) and the **fence** (possible
data loss, noticed atomically with a commit, raises it to that moment, in the
shared state so every replica applies it).

Backends: :mod:`.memory` (one process), :mod:`.sqlite` (one machine, survives
``kill -9`` and reboots), :mod:`.redis` (replicas; standalone or Cluster, fails
closed).  One grammar names them, :meth:`StoreSpec.parse` (:mod:`.spec`:
``memory``, ``sqlite:PATH``, ``redis://``, ``rediss://``, ``unix://``,
``redis+cluster://``); :func:`open_store` opens one.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any, Protocol, runtime_checkable

from antireplay.core.clock import Clock
from antireplay.core.window import Seen
from antireplay.state.spec import ALLOWED, StoreSpec

#: Runs ``fn(*args)`` in a thread for a running event loop to await: the one hand-off to a
#: thread (the gateway passes its worker pool; :func:`in_executor` by default).
Offload = Callable[..., Awaitable[Any]]


def in_executor(fn: Callable[..., Any], *args: Any) -> Awaitable[Any]:
    """The default :data:`Offload`: the running loop's default executor."""
    return asyncio.get_running_loop().run_in_executor(None, fn, *args)


def offloaded(offload: Offload | None, commit: Callable[..., Seen], *args: Any) -> Awaitable[Seen]:
    """``commit_async`` of a store whose ``commit`` blocks: ``commit(*args)`` in a thread."""
    result: Awaitable[Seen] = (offload or in_executor)(commit, *args)
    return result


@runtime_checkable
class ReplayStore(Protocol):
    """Atomic replay state; see the module docstring for the contract."""

    @property
    def backend(self) -> str:
        """``memory``, ``sqlite``, ``redis`` or ``redis-cluster`` (a metrics label)."""

    def lookup(self, key: str) -> Seen: ...

    def fence(self) -> float:
        """The fence as last known to this process (no I/O)."""

    def watermark(self) -> float:
        """The watermark as last known to this process (no I/O)."""

    def commit(self, key: str, expires_at: float, now: float, force: bool = False) -> Seen: ...

    def commit_async(
        self,
        key: str,
        expires_at: float,
        now: float,
        force: bool = False,
        offload: Offload | None = None,
    ) -> Awaitable[Seen]:
        """:meth:`commit` from a running event loop (a blocking one runs in ``offload``)."""

    def verify(self) -> Seen:
        """Run this backend's loss detection now; the fence and watermark it finds."""

    def advance(self, key: str, value: int) -> bool: ...

    def current(self, key: str) -> int | None: ...

    def status(self) -> dict[str, float]: ...

    def ready(self) -> None:
        """Raise ``StateUnavailableError`` unless a commit could go through now; records nothing."""

    def close(self) -> None: ...


#: The store specs :meth:`StoreSpec.parse` accepts, in words (for errors and the docs).
STORE_SPECS = ALLOWED


def open_store(
    spec: str | StoreSpec,
    *,
    clock: Clock | None = None,
    max_entries: int = 10_000,
    skew_s: float = 5.0,
) -> ReplayStore:
    """Build a store from its spec (:meth:`StoreSpec.parse`); ``max_entries`` bounds the
    memory backend."""
    parsed = spec if isinstance(spec, StoreSpec) else StoreSpec.parse(spec)
    return parsed.open(clock=clock, max_entries=max_entries, skew_s=skew_s)


__all__ = [
    "STORE_SPECS",
    "Offload",
    "ReplayStore",
    "Seen",
    "StoreSpec",
    "in_executor",
    "offloaded",
    "open_store",
]
