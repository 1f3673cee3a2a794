"""The timestamps a MAVLink signer stamps: pure values, persisted by their driver.

Theory of operation
-------------------
A link's signing timestamp is tied to real time: the next one is ``max(last + 1, now)``
(``now`` in MAVLink units, given by the caller), never ``2**48`` or past it
(``NONCE_EXHAUSTED``: rekey the link).  A signer that must never repeat a timestamp
across restarts (the MAVLink spec's rule), whatever the wall clock did, hands out only
timestamps at or below a **reserved ceiling** that is durable: :meth:`SignTimestamps.take`
answers a :class:`Reserve` (the ceiling to persist first) instead of a timestamp above it,
and :meth:`SignTimestamps.reserved` raises the ceiling once the driver made it durable.
:meth:`SignTimestamps.due` says when a timer should reserve ahead, so that the signing
path rarely waits for the store.  :func:`resume_after` is where a restarted signer starts:
above its stored ceiling, and after a store data loss above the loss time plus the
reserve.  No store, lock or clock here: :mod:`antireplay.mavlink.signer` drives it.
"""

from __future__ import annotations

from dataclasses import dataclass

from antireplay.core.errors import NonceExhaustedError
from antireplay.core.window import NEVER
from antireplay.mavlink.codec import MAV_EPOCH, TS_LIMIT, UNITS_PER_S


@dataclass(frozen=True, slots=True)
class Reserve:
    """Persist ``ceiling`` (and report it with :meth:`SignTimestamps.reserved`) first."""

    ceiling: int


def resume_after(stored: int | None, lost: float, reserve: int, last: int = 0) -> int:
    """The last timestamp a restarted signer may have used: its stored ceiling, or after a
    store data loss at wall time ``lost`` (``NEVER``: none), the loss time plus ``reserve``."""
    last = max(last, stored or 0)
    if lost != NEVER:  # the store forgot its ceiling: resume above what it could hold
        last = max(last, int((lost - MAV_EPOCH) * UNITS_PER_S) + reserve)
    return last


class SignTimestamps:
    """One link's signing timestamps (module docstring); not thread-safe: the driver
    serializes.  ``reserve`` 0: nothing is persisted (no ceiling)."""

    def __init__(self, last: int = 0, *, reserve: int = 0) -> None:
        if last + 1 >= TS_LIMIT:
            raise NonceExhaustedError("MAVLink timestamp reached 2**48; rekey the link")
        self.last = last
        self.reserve = reserve
        #: Timestamps up to here may be handed out (persisted when ``reserve``).
        self.ceiling = last if reserve else TS_LIMIT - 1

    def take(self, now: int) -> int | Reserve:
        """The next timestamp at ``now``, or the ceiling to persist before it."""
        value = max(self.last + 1, now)
        if value >= TS_LIMIT:
            raise NonceExhaustedError("MAVLink timestamp reached 2**48; rekey the link")
        if value > self.ceiling:
            return Reserve(min(value + self.reserve - 1, TS_LIMIT - 1))
        self.last = value
        return value

    def due(self, now: int) -> Reserve | None:
        """What a timer should reserve now so that the next ``reserve`` of signing finds a
        durable ceiling (None: the ceiling is far enough ahead, or nothing is persisted)."""
        if not self.reserve:
            return None
        value = max(self.last + 1, now)
        if value + self.reserve // 2 <= self.ceiling:
            return None
        return Reserve(min(value + self.reserve - 1, TS_LIMIT - 1))

    def reserved(self, ceiling: int) -> None:
        """``ceiling`` is durable: timestamps up to it may be handed out."""
        self.ceiling = max(self.ceiling, ceiling)

    def resume(self, stored: int) -> None:
        """The store holds ``stored`` (a co-owner wrote it): go on above it."""
        self.last = max(self.last, stored)
