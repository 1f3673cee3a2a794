"""Clocks: the only way antireplay's policies learn the time.

Theory of operation
-------------------
Policies never call :func:`time.time`; they take a :class:`Clock`.  A clock has
two faces: ``wall()`` (Unix seconds, used to judge the freshness of a sender's
timestamp, and able to step when NTP corrects it) and ``monotonic()`` (never
steps, used for rate limits and leases).  Production code uses
:class:`SystemClock`; tests use :class:`ManualClock` and move time explicitly,
including wall-clock steps backwards, instead of sleeping.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """Wall time (may step) and monotonic time (never steps), both in seconds."""

    def wall(self) -> float: ...

    def monotonic(self) -> float: ...


class SystemClock:
    """The host's clocks (the C functions themselves: no extra Python frame per reading)."""

    wall = staticmethod(time.time)
    monotonic = staticmethod(time.monotonic)


class ManualClock:
    """A clock that moves only when told to; thread-safe so races can share it."""

    def __init__(self, wall: float = 1_700_000_000.0, monotonic: float = 1_000.0) -> None:
        self._wall = float(wall)
        self._mono = float(monotonic)
        self._lock = threading.Lock()

    def wall(self) -> float:
        return self._wall

    def monotonic(self) -> float:
        return self._mono

    def advance(self, seconds: float) -> None:
        """Let time pass: both faces move forward by ``seconds``."""
        if seconds < 0:
            raise ValueError("time does not run backwards; use step_wall() for a wall-clock step")
        with self._lock:
            self._wall += seconds
            self._mono += seconds

    def step_wall(self, seconds: float) -> None:
        """Step only the wall clock (as NTP does), forwards or backwards."""
        with self._lock:
            self._wall += seconds


def resolve(clock: Clock | None) -> Clock:
    """``None`` means the system clock."""
    return SystemClock() if clock is None else clock
