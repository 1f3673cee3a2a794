"""Signing timestamps, pure: a manual time in, the next timestamp or the ceiling to persist
first out."""

from __future__ import annotations

import pytest

from antireplay.core.errors import NonceExhaustedError
from antireplay.core.window import NEVER
from antireplay.mavlink import MAV_EPOCH, TS_LIMIT, UNITS_PER_S
from antireplay.mavlink.signing import Reserve, SignTimestamps, resume_after

S = UNITS_PER_S
NOW = 300_000 * S


@pytest.mark.parametrize(
    ("last", "now", "expected"),
    [
        (0, NOW, NOW),  # tied to the clock
        (NOW, NOW, NOW + 1),  # never the same twice
        (NOW + 5 * S, NOW, NOW + 5 * S + 1),  # the clock stepped back: still increasing
        (TS_LIMIT - 2, TS_LIMIT + 9, NonceExhaustedError),  # never 2**48
    ],
)
def test_the_next_timestamp(last: int, now: int, expected: int | type[Exception]) -> None:
    value = SignTimestamps(last)
    if isinstance(expected, int):
        assert value.take(now) == expected and value.last == expected
    else:
        with pytest.raises(expected):
            value.take(now)


def test_a_persisted_value_hands_out_nothing_above_its_durable_ceiling() -> None:
    value = SignTimestamps(NOW - S, reserve=S)
    assert value.take(NOW) == Reserve(NOW + S - 1)
    assert value.last == NOW - S  # nothing handed out before the ceiling is durable
    value.reserved(NOW + S - 1)
    assert value.take(NOW) == NOW
    assert value.take(NOW + S - 1) == NOW + S - 1
    assert value.take(NOW + S - 1) == Reserve(NOW + 2 * S - 1)


@pytest.mark.parametrize(
    ("ceiling", "now", "due"),
    [
        (NOW + S, NOW, None),  # a whole reserve ahead
        (NOW + S // 2, NOW, None),  # half a reserve ahead: still enough
        (NOW + S // 2 - 1, NOW, Reserve(NOW + S - 1)),  # less: the timer reserves
    ],
)
def test_when_the_timer_reserves_ahead(ceiling: int, now: int, due: Reserve | None) -> None:
    value = SignTimestamps(NOW - S, reserve=S)
    value.reserved(ceiling)
    assert value.due(now) == due
    assert SignTimestamps(NOW - S).due(now) is None  # nothing persisted: never due


def test_a_restarted_signer_resumes_above_its_ceiling_or_a_store_loss() -> None:
    assert resume_after(None, NEVER, S) == 0
    assert resume_after(NOW, NEVER, S, last=5) == NOW
    lost_at = MAV_EPOCH + NOW / S  # the store lost its data at NOW
    assert resume_after(None, lost_at, S) == NOW + S
    value = SignTimestamps(NOW)
    value.resume(NOW + 7)  # a co-owner went higher
    assert value.take(NOW) == NOW + 8
