"""A MAVLink signer's timestamp source: :mod:`antireplay.mavlink.signing` driven by a clock
and persisted in a store.

Theory of operation
-------------------
:class:`TimestampSource` keeps a link's timestamp tied to real time (``max(last + 1,
now)``, :class:`~antireplay.mavlink.signing.SignTimestamps`) and raises
``NonceExhaustedError`` at ``2**48`` instead of truncating.  Given a store it is durable,
by lease: it hands out timestamps only below a ceiling reserved ``reserve_s`` ahead in the
store (one store write per ``reserve_s`` of signing), and a new source starts above the
stored ceiling, so a restarted signer never repeats a timestamp, whatever the wall clock
did; after a store data loss it starts above the loss time plus the reserve.  Its owner's
timer calls :meth:`TimestampSource.tick` (the router's timer does) to reserve ahead before
the signing path reaches the ceiling; the signing path reserves itself when the timer is
late.  Its lock is held only around the pure value, never across the store write.
"""

from __future__ import annotations

import threading

from antireplay.core.clock import Clock, resolve
from antireplay.mavlink.codec import UNITS_PER_S, mav_time
from antireplay.mavlink.signing import Reserve, SignTimestamps, resume_after
from antireplay.state import ReplayStore


class TimestampSource:
    """A sender's link timestamps, anchored to MAVLink time, never past ``2**48``; with a
    store, never repeating across restarts (module docstring)."""

    def __init__(
        self,
        clock: Clock | None = None,
        last: int = 0,
        *,
        store: ReplayStore | None = None,
        store_key: str = "mav-sign",
        reserve_s: float = 1.0,
    ) -> None:
        self.clock = resolve(clock)
        self.store, self.store_key = store, store_key
        reserve = int(reserve_s * UNITS_PER_S) if store is not None else 0
        if store is not None:
            last = resume_after(store.current(store_key), store.verify().fence, reserve, last)
        self._value = SignTimestamps(last, reserve=reserve)
        self._lock = threading.Lock()
        #: Ceilings persisted so far (one per ``reserve_s`` of signing): the write cost.
        self.reservations = 0

    @property
    def last(self) -> int:
        """The last timestamp handed out."""
        return self._value.last

    def next(self) -> int:
        """The next timestamp (persisting a new ceiling first when it reaches the last)."""
        while True:
            now = mav_time(self.clock)
            with self._lock:
                step = self._value.take(now)
            if not isinstance(step, Reserve):
                return step
            self._reserve(step)

    def tick(self) -> None:
        """The owner's timer: reserve ahead if the ceiling is near (module docstring)."""
        with self._lock:
            step = self._value.due(mav_time(self.clock))
        if step is not None:
            self._reserve(step)

    def _reserve(self, step: Reserve) -> None:
        """Make ``step.ceiling`` durable (no lock held), then let the value use it."""
        assert self.store is not None  # only a persisted value asks
        if not self.store.advance(self.store_key, step.ceiling):
            stored = self.store.current(self.store_key) or 0  # a stray co-owner went higher
            with self._lock:
                self._value.resume(stored)
            return
        self.reservations += 1
        with self._lock:
            self._value.reserved(step.ceiling)
