"""The handshake budget alone: backoff and airtime on a manual clock."""

from __future__ import annotations

import random

from antireplay import ManualClock
from antireplay.mavlink.pq.budget import POKE_BYTES, HandshakeBudget
from antireplay.mavlink.pq.wire import share_rate


def test_the_first_hs1_always_fits_and_the_next_waits_for_its_share(clock: ManualClock) -> None:
    budget = HandshakeBudget(clock, retry_s=2.0, air_bps=57_600, rng=random.Random(1))
    budget.attempt(7_500)
    assert budget.bucket.burst == 7_500 and not budget.holds_hs1()
    clock.advance(7_500 / share_rate(57_600) - 0.1)
    assert not budget.holds_hs1()
    clock.advance(0.2)
    assert budget.holds_hs1()


def test_backoff_doubles_to_its_cap_and_proof_resets_it(clock: ManualClock) -> None:
    budget = HandshakeBudget(clock, retry_s=2.0, max_backoff_s=10.0, rng=random.Random(3))
    for base in (2.0, 4.0, 8.0, 10.0, 10.0):
        budget.attempt(100)
        assert 0.75 * base <= budget.backoff <= base
    budget.proven()
    assert budget.attempts == 0 and budget.backoff == 2.0
    assert budget.bucket.tokens == budget.bucket.burst


def test_an_unsigned_nack_resends_each_chunk_once_per_attempt(clock: ManualClock) -> None:
    budget = HandshakeBudget(clock, air_bps=10_000_000)
    budget.attempt(1_000)
    clock.advance(10.0)
    unsigned, signed = budget.affords(False), budget.affords(True)
    assert unsigned(b"chunk") and not unsigned(b"chunk")
    assert signed(b"chunk") and signed(b"chunk")
    budget.attempt(1_000)
    clock.advance(10.0)
    assert budget.affords(False)(b"chunk")  # a new attempt: once more
    assert budget.take_poke() and POKE_BYTES == 35
