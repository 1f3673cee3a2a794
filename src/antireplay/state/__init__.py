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
* ``forget(keys, fence_key, fence)``: one atomic step that raises counter ``fence_key``
  to ``fence`` and deletes the counters ``keys``: bounded counter state (the epoch
  verifier's evicted prefixes) that never re-opens a replay, as the fence covers them;
  ``advance_above(key, value, fence_key)`` advances only above that fence too, in the
  same atomic step (another process may have just forgotten the counter).
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
``redis+cluster://``); :func:`open_store` opens one.  A SQLite store may keep a
:mod:`.anchor` outside its directory, so that a restored copy of the whole directory is a
detected loss too.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from antireplay.core.clock import Clock
from antireplay.core.window import Seen
from antireplay.state.contract import Offload, ReplayStore, in_executor, offloaded
from antireplay.state.spec import ALLOWED, StoreSpec

if TYPE_CHECKING:
    from antireplay.state.anchor import StateAnchor

#: The store specs :meth:`StoreSpec.parse` accepts, in words (for errors and the docs).
STORE_SPECS = ALLOWED


def open_store(
    spec: str | StoreSpec,
    *,
    clock: Clock | None = None,
    max_entries: int = 10_000,
    skew_s: float = 5.0,
    anchor: StateAnchor | None = None,
) -> ReplayStore:
    """Build a store from its spec (:meth:`StoreSpec.parse`); ``max_entries`` bounds the
    memory backend; ``anchor`` (:mod:`.anchor`) is a SQLite store's, outside its directory."""
    parsed = spec if isinstance(spec, StoreSpec) else StoreSpec.parse(spec)
    if anchor is not None and parsed.backend != "sqlite":
        raise ValueError(f"a state anchor is a sqlite store's, not a {parsed.backend} store's")
    if parsed.backend == "memory":
        from antireplay.state.memory import MemoryStore  # noqa: PLC0415 - optional backends

        return MemoryStore(max_entries=max_entries, clock=clock)
    if parsed.backend == "sqlite":
        from antireplay.state.sqlite import SqliteStore  # noqa: PLC0415

        return SqliteStore(parsed.target, clock=clock, anchor=anchor)
    from antireplay.state.redis import RedisStore  # noqa: PLC0415

    return RedisStore(parsed.text, clock=clock, skew_s=skew_s)


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
