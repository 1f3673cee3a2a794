"""A token bucket: how often something costly (an audit row, a log line) may happen.

Refusals of malformed or unauthenticated input are counted always, but written to
the audit trail or the log at most ``rate`` times a second, so a flood cannot fill
the disk.  The bucket holds its own lock; time comes from the injected clock.
"""

from __future__ import annotations

import threading

from antireplay.core.clock import Clock


class TokenBucket:
    """Rate limit for auditing input that is malformed or unauthenticated (``rate`` per s)."""

    def __init__(self, rate: float, clock: Clock) -> None:
        self.rate, self.clock = rate, clock
        self.tokens, self.stamp = rate, clock.monotonic()
        self._lock = threading.Lock()

    def take(self) -> bool:
        with self._lock:
            now = self.clock.monotonic()
            self.tokens = min(self.rate, self.tokens + (now - self.stamp) * self.rate)
            self.stamp = now
            if self.tokens >= 1:
                self.tokens -= 1
                return True
            return False
