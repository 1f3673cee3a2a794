"""The air a failing handshake may take, and the backoff between attempts (the ground end).

Theory of operation
-------------------
Sans-I/O arithmetic for :class:`~.ground.GroundEnd`: sizes and a clock in, yes or no out.
A handshake that fails costs little air (:data:`~.wire.HANDSHAKE_SHARE`).  Attempts back
off exponentially from ``retry_s`` (doubling to ``max_backoff_s``, each shortened by at most
a quarter by this end's own randomness, so that ground ends never fall into step).  HS1s,
their POKEs and their repairs draw on one token bucket: over any window of ``W`` s at most
``HANDSHAKE_SHARE * air_bps / 10 * W`` bytes plus one HS1 with its parity (the bucket's
burst, grown to the first HS1's size), so 5 % in the long run at every line rate.

A session refills the bucket and resets the backoff (:meth:`HandshakeBudget.proven`) only
once it carried authenticated vehicle traffic: an idle or dead vehicle end that still
answers HS1s keeps the ground end within the budget.  An unsigned NACK (anyone can send
one) resends each HS1 chunk once per attempt (:meth:`HandshakeBudget.affords`).
"""

from __future__ import annotations

import random
from collections.abc import Callable

from antireplay.core.clock import Clock
from antireplay.core.ratelimit import TokenBucket
from antireplay.mavlink.pq.wire import MAX_BACKOFF_S, share_rate

POKE_BYTES = 35  # a PQ_REPAIR on the air


class HandshakeBudget:
    """One ground end's handshake backoff and airtime bucket (module docstring)."""

    def __init__(
        self,
        clock: Clock,
        retry_s: float = 2.0,
        max_backoff_s: float = MAX_BACKOFF_S,
        air_bps: int | None = None,
        rng: random.Random | None = None,
    ) -> None:
        for name, value in (("retry_s", retry_s), ("max_backoff_s", max_backoff_s)):
            if not value > 0:
                raise ValueError(f"{name} must be positive seconds, not {value}")
        if air_bps is not None and air_bps <= 0:
            raise ValueError(f"air_bps must be positive (baud), or None for unknown: {air_bps}")
        self.retry_s, self.max_backoff_s = retry_s, max_backoff_s
        self._rng = rng or random.SystemRandom()  # the backoff's jitter
        self.attempts = 0  # handshakes started since the last session proved itself
        self.backoff = retry_s  # quiet before the next attempt (doubling, jittered)
        self.hs_size = 0  # the last HS1's air bytes
        self.bucket = TokenBucket(share_rate(air_bps), clock, burst=0.0)
        self._resent: set[bytes] = set()  # HS1 chunks resent on unsigned NACKs (once each)

    def attempt(self, hs_size: int) -> None:
        """A new HS1 of ``hs_size`` air bytes leaves: back off further and charge it (the
        bucket's burst grows to one HS1 at the first, so the first one always fits)."""
        base = min(self.retry_s * 2 ** min(self.attempts, 32), self.max_backoff_s)
        self.backoff = base * self._rng.uniform(0.75, 1.0)
        self.attempts += 1
        self.hs_size = hs_size
        self._resent = set()
        if hs_size > self.bucket.burst:
            self.bucket.tokens += hs_size - self.bucket.burst
            self.bucket.burst = hs_size
        self.bucket.spend(hs_size)

    def holds_hs1(self) -> bool:
        """Whether the bucket holds another HS1 like the last one now."""
        return self.bucket.wait_s(self.hs_size) <= 0

    def take_poke(self) -> bool:
        """Charge one POKE, if the bucket holds it."""
        return self.bucket.take(POKE_BYTES)

    def affords(self, signed: bool) -> Callable[[bytes], bool]:
        """Whether an HS1 chunk may be resent: within the budget, and once per attempt when
        the NACK asking for it is unsigned (anyone can send one)."""

        def afford(raw: bytes) -> bool:
            if not signed and raw in self._resent:
                return False
            if not self.bucket.take(len(raw)):
                return False
            if not signed:
                self._resent.add(raw)
            return True

        return afford

    def proven(self) -> None:
        """A session carried authenticated vehicle traffic: full bucket, backoff from scratch."""
        self.attempts = 0
        self.backoff = self.retry_s
        self.bucket.tokens = self.bucket.burst
