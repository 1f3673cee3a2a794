"""A token bucket: how often something costly (an audit row, a log line) may happen.

Refusals of malformed or unauthenticated input are counted always, but written to
the audit trail or the log at most ``rate`` times a second, so a flood cannot fill
the disk.  The bucket holds its own lock; time comes from the injected clock.
"""

from __future__ import annotations

import threading

from antireplay.core.clock import Clock


class TokenBucket:
    """Rate limit for auditing input that is malformed or unauthenticated (``rate`` per s);
    ``burst`` tokens at most (``rate``: one second's), ``cost`` per take (bytes on a radio)."""

    def __init__(self, rate: float, clock: Clock, burst: float | None = None) -> None:
        self.rate, self.clock = rate, clock
        self.burst = rate if burst is None else burst
        self.tokens, self.stamp = self.burst, clock.monotonic()
        self._lock = threading.Lock()

    def take(self, cost: float = 1.0) -> bool:
        with self._lock:
            now = self.clock.monotonic()
            self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
            self.stamp = now
            if self.tokens >= cost:
                self.tokens -= cost
                return True
            return False

    def spend(self, cost: float) -> None:
        """Take ``cost`` tokens whatever the bucket holds (into debt: what must go, goes)."""
        if not self.take(cost):
            with self._lock:
                self.tokens -= cost

    def wait_s(self, cost: float = 1.0) -> float:
        """Seconds until ``cost`` tokens are there (0 when they are now)."""
        with self._lock:
            held = self.tokens + (self.clock.monotonic() - self.stamp) * self.rate
            return max(0.0, (min(cost, self.burst) - held) / self.rate)
