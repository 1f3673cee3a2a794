"""A signer's timestamp source: tied to the clock, durable by a reserved ceiling, reserved
ahead by its owner's timer."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from antireplay import ManualClock
from antireplay.core.errors import NonceExhaustedError
from antireplay.mavlink import TS_LIMIT, UNITS_PER_S, TimestampSource, mav_time
from antireplay.state.sqlite import SqliteStore


class CountingStore:
    """A store wrapper that counts ``advance`` calls."""

    def __init__(self, inner: SqliteStore) -> None:
        self.inner = inner
        self.writes = 0

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def advance(self, key: str, value: int) -> bool:
        self.writes += 1
        return self.inner.advance(key, value)


def test_timestamp_source_tracks_time_and_refuses_wrap(clock: ManualClock) -> None:
    source = TimestampSource(clock)
    a, b = source.next(), source.next()
    assert a == mav_time(clock) and b == a + 1
    clock.advance(1)
    assert source.next() == mav_time(clock)
    with pytest.raises(NonceExhaustedError):
        TimestampSource(clock, last=TS_LIMIT - 1).next()


def test_durable_timestamp_source_never_repeats_across_restarts(
    tmp_path: Path, clock: ManualClock
) -> None:
    store = SqliteStore(tmp_path / "sign.db")
    first = TimestampSource(clock, store=store, store_key="sign")
    handed = [first.next() for _ in range(1_000)]
    assert store.current("sign") == max(handed) - 999 + UNITS_PER_S - 1  # one write per second
    clock.step_wall(-30)  # the wall clock steps back (NTP) across a restart
    again = TimestampSource(clock, store=store, store_key="sign")
    assert again.next() > max(handed)
    store.close()


def test_the_owners_timer_reserves_ahead_so_signing_does_not_write(
    tmp_path: Path, clock: ManualClock
) -> None:
    """Ticked every half reserve, a source signing 100 frames a second for 5 s writes only
    from its tick, never on the signing path; untouched, the signing path reserves itself."""
    store = CountingStore(SqliteStore(tmp_path / "sign.db"))
    source = TimestampSource(clock, store=store, store_key="sign")
    source.tick()
    signing_path = 0
    for i in range(500):
        before = store.writes
        source.next()
        signing_path += store.writes - before
        clock.advance(0.01)
        if i % 50 == 49:
            source.tick()
    assert signing_path == 0 and 5 <= source.reservations <= 11
    late = TimestampSource(clock, store=store, store_key="late")
    late.next()  # no tick yet: the signing path reserves before it hands a value out
    assert late.reservations == 1 and store.current("late") >= late.last
    store.close()
