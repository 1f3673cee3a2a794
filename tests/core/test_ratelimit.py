"""The token bucket: a rate, a burst, a cost per take, and how long until the next."""

from __future__ import annotations

from antireplay import ManualClock
from antireplay.core.ratelimit import TokenBucket


def test_one_token_a_take_at_most_rate_a_second() -> None:
    clock = ManualClock()
    bucket = TokenBucket(3.0, clock)
    assert [bucket.take() for _ in range(4)] == [True, True, True, False]
    clock.advance(1 / 3)
    assert bucket.take() and not bucket.take()


def test_bytes_with_a_burst_and_the_wait_for_the_next() -> None:
    clock = ManualClock()
    bucket = TokenBucket(1_000.0, clock, burst=300.0)  # bytes a second, 300 at once
    assert bucket.take(250) and not bucket.take(100)
    assert abs(bucket.wait_s(100) - 0.05) < 1e-9  # 50 held, 50 more in 50 ms
    clock.advance(10)  # idle: the burst caps what builds up
    assert bucket.take(300) and not bucket.take(1)
    assert bucket.wait_s(1_000) == 0.3  # asking for more than the burst waits for the burst
