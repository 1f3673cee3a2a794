"""Replay state stores: one contract that carries the safety, three backends that keep it.

Theory of operation
-------------------
The policies decide; a store keeps their state and offers the few **atomic**
operations they need, so threads, processes or replicas sharing one store accept
each message exactly once (:class:`ReplayStore`):

* ``lookup`` records nothing (the pre-crypto check); ``commit`` atomically records a
  key unless it has a live entry (``force``, a fresh ESTOP, extends it); two racers:
  exactly one ``recorded``.  ``advance``/``current``: compare-and-advance counters.
* ``verify`` runs the loss detection now; ``status`` gives figures for ``/metrics``.
* ``ready`` is the one readiness probe: it raises ``STATE_UNAVAILABLE`` unless a
  commit could go through now, and records nothing (it never notices a loss in
  place of the commit that fences and audits it).

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

from typing import Protocol, runtime_checkable

from antireplay.core.clock import Clock
from antireplay.core.window import Seen
from antireplay.state.spec import ALLOWED, StoreSpec


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


__all__ = ["STORE_SPECS", "ReplayStore", "Seen", "StoreSpec", "open_store"]
