"""Sender counters, strict trackers, RFC 6479 windows (WireGuard vectors) and stream tables."""

from __future__ import annotations

import itertools
import threading
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from antireplay.counters import (
    COUNTER_LIMIT,
    DEFAULT_WINDOW,
    CounterWindow,
    NonceCounter,
    NonceTracker,
    StreamTable,
)
from antireplay.errors import (
    CounterLimitError,
    CounterReplayError,
    CounterTooOldError,
    NonceExhaustedError,
    SessionClosedError,
)
from tests.conftest import assert_never_reused, kill9_runs, race, run_threads

# --- the three CleitonQ properties, ported ----------------------------------------------------


def test_eight_threads_thousand_next_are_distinct() -> None:
    counter = NonceCounter()
    values: list[list[int]] = [[] for _ in range(8)]
    run_threads(8, lambda i: values[i].extend(counter.next() for _ in range(1_000)))
    flat = [v for vs in values for v in vs]
    assert len(set(flat)) == 8_000
    assert all(a < b for vs in values for a, b in itertools.pairwise(vs))


def test_tracker_sequence_5_5_3_6() -> None:
    tracker = NonceTracker()
    assert [tracker.accept(n) for n in (5, 5, 3, 6)] == [True, False, False, True]
    assert tracker.last_accepted == 6


def test_four_threads_offering_1_to_500_give_500_acceptances() -> None:
    tracker = NonceTracker()
    accepted: list[int] = []
    lock = threading.Lock()

    def offer(_: int) -> None:
        for n in range(1, 501):
            if tracker.accept(n):
                with lock:
                    accepted.append(n)

    run_threads(4, offer)
    assert len(accepted) == 500
    assert sorted(accepted) == list(range(1, 501))
    assert tracker.last_accepted == 500


def test_tracker_check_does_not_mutate() -> None:
    tracker = NonceTracker(last=10)
    tracker.check(11)
    tracker.check(11)
    assert tracker.last_accepted == 10
    with pytest.raises(CounterReplayError):
        tracker.check(10)


# --- sender counter ---------------------------------------------------------------------------


def test_counter_raises_at_limit_instead_of_wrapping() -> None:
    counter = NonceCounter(start=COUNTER_LIMIT - 2)
    assert counter.next() == COUNTER_LIMIT - 2
    assert counter.next() == COUNTER_LIMIT - 1
    with pytest.raises(NonceExhaustedError):
        counter.next()
    with pytest.raises(NonceExhaustedError):
        counter.next()


def test_counter_rejects_bad_start() -> None:
    for bad in (-1, COUNTER_LIMIT, True, 1.5):
        with pytest.raises(ValueError, match="start"):
            NonceCounter(start=bad)  # type: ignore[arg-type]


def test_counter_from_time_is_above_time_ns() -> None:
    before = time.time_ns()
    assert NonceCounter.from_time().next() >= before


def test_persistent_counter_writes_once_per_lease(tmp_path: Path) -> None:
    path = tmp_path / "ctr.state"
    counter = NonceCounter.persistent(path, lease=100)
    values = [counter.next() for _ in range(1_000)]
    assert values == list(range(1, 1_001))
    assert counter._state is not None
    assert counter._state.writes == 10


def test_persistent_counter_resumes_above_ceiling(tmp_path: Path) -> None:
    path = tmp_path / "ctr.state"
    first = NonceCounter.persistent(path, lease=50)
    used = [first.next() for _ in range(7)]
    first.close()
    second = NonceCounter.persistent(path, lease=50)  # as after a crash: 43 leased values skipped
    assert second.next() > max(used)
    assert second.next() == 52


def test_persistent_counter_never_reuses_across_kill9(tmp_path: Path) -> None:
    """100 real subprocesses, each SIGKILLed at a random moment."""
    args = ["-m", "tests.helpers.counter_worker", str(tmp_path / "ctr.state"), "16"]
    assert_never_reused(kill9_runs(args, 100, 120, seed=1234), "counter")


# --- CounterWindow: WireGuard's published vectors (size 8128, limit 2**64 - 2**4 - 1) ----------

WG_LIMIT = 2**64 - 2**4 - 1
T_LIM = DEFAULT_WINDOW + 1
WG_VECTORS: list[tuple[int, bool]] = [
    (0, True), (1, True), (1, False), (9, True), (8, True), (7, True), (7, False),
    (T_LIM, True), (T_LIM - 1, True), (T_LIM - 1, False), (T_LIM - 2, True), (2, True),
    (2, False), (T_LIM + 16, True), (3, False), (T_LIM + 16, False), (T_LIM * 4, True),
    (T_LIM * 4 - (T_LIM - 1), True), (10, False), (T_LIM * 4 - T_LIM, False),
    (T_LIM * 4 - (T_LIM + 1), False), (T_LIM * 4 - (T_LIM - 2), True),
    (T_LIM * 4 + 1 - T_LIM, False), (0, False), (WG_LIMIT, False), (WG_LIMIT - 1, True),
    (WG_LIMIT, False), (WG_LIMIT - 1, False), (WG_LIMIT - 2, True), (WG_LIMIT + 1, False),
    (WG_LIMIT + 2, False), (WG_LIMIT - 2, False), (WG_LIMIT - 3, True), (0, False),
]  # fmt: skip


def test_wireguard_vectors() -> None:
    window = CounterWindow(DEFAULT_WINDOW, limit=WG_LIMIT)
    for number, (counter, expected) in enumerate(WG_VECTORS, start=1):
        assert window.accept(counter) is expected, f"vector {number}: {counter}"


def test_wireguard_vectors_check_agrees_with_accept() -> None:
    window = CounterWindow(DEFAULT_WINDOW, limit=WG_LIMIT)
    for counter, expected in WG_VECTORS:
        try:
            window.check(counter)
            predicted = True
        except (CounterReplayError, CounterTooOldError, CounterLimitError):
            predicted = False
        assert predicted is expected
        assert window.accept(counter) is expected


def _bulk(counters: list[int], tail: list[tuple[int, bool]]) -> None:
    window = CounterWindow(DEFAULT_WINDOW, limit=WG_LIMIT)
    for c in counters:
        assert window.accept(c), c
    for c, expected in tail:
        assert window.accept(c) is expected, c


W = DEFAULT_WINDOW


def test_wireguard_bulk_vectors() -> None:
    _bulk(list(range(1, W + 1)), [(0, True), (0, False)])
    _bulk(list(range(2, W + 2)), [(1, True), (0, False)])
    _bulk(list(range(W + 1, 0, -1)), [])
    _bulk(list(range(W + 2, 1, -1)), [(0, False)])
    _bulk(list(range(W, 0, -1)), [(W + 1, True), (0, False)])
    _bulk(list(range(W, 0, -1)), [(0, True), (W + 1, True)])


def test_counter_zero_valid_on_fresh_window() -> None:
    window = CounterWindow()
    window.check(0)
    assert window.accept(0)
    with pytest.raises(CounterReplayError):
        window.check(0)


def test_reordering_within_window_accepted_once() -> None:
    window = CounterWindow()
    order = [5, 3, 4, 1, 2, 100, 50, 99]
    assert all(window.accept(c) for c in order)
    assert not any(window.accept(c) for c in order)


def test_check_is_typed_and_does_not_mutate() -> None:
    window = CounterWindow()
    window.check(10_000)
    assert window.last == 0
    window.accept(10_000)
    with pytest.raises(CounterTooOldError):
        window.check(10_000 - DEFAULT_WINDOW - 1)
    with pytest.raises(CounterLimitError):
        window.check(COUNTER_LIMIT)
    with pytest.raises(CounterLimitError):
        window.check(-1)


def test_window_race_has_one_winner() -> None:
    window = CounterWindow()
    for c in range(100):
        wins: list[int] = []

        def offer(_: int, value: int = c, w: list[int] = wins) -> None:
            if window.accept(value):
                w.append(value)

        run_threads(4, offer)
        assert len(wins) == 1


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.integers(0, 20_000),
            st.integers(COUNTER_LIMIT - 20_000, COUNTER_LIMIT + 5),
        ),
        max_size=300,
    )
)
def test_property_each_counter_accepted_at_most_once(counters: list[int]) -> None:
    window = CounterWindow()
    accepted: set[int] = set()
    for c in counters:
        last = window.last
        if window.accept(c):
            assert c not in accepted, "a counter was accepted twice"
            assert c < COUNTER_LIMIT
            assert c > last or last - c <= DEFAULT_WINDOW
            accepted.add(c)
        else:
            assert c in accepted or c >= COUNTER_LIMIT or last - c > DEFAULT_WINDOW


# --- stream tables ----------------------------------------------------------------------------


def test_stream_table_is_bounded_and_fences_evicted_streams() -> None:
    table = StreamTable(max_streams=3)
    for seq in (1, 2, 3):
        table.accept("gcs", seq, 0)
    table.accept("gcs", 4, 0)  # evicts seq 1, the oldest session
    assert len(table) == 3
    assert table.fence == 1
    with pytest.raises(SessionClosedError):
        table.check("gcs", 1, 0)  # the evicted stream's capture cannot come back
    with pytest.raises(SessionClosedError):
        table.accept("gcs", 1, 5)
    with pytest.raises(CounterReplayError):
        table.accept("gcs", 4, 0)


def test_stream_check_creates_nothing() -> None:
    table = StreamTable(max_streams=2)
    table.check("gcs", 1, 10**18)
    assert len(table) == 0


def test_closed_stream_stays_closed() -> None:
    table = StreamTable()
    table.accept("gcs", 7, 0)
    table.close("gcs", 7)
    with pytest.raises(SessionClosedError):
        table.accept("gcs", 7, 1)


def test_stream_accept_race_one_winner() -> None:
    table = StreamTable()
    for counter in range(50):
        wins, losses = race(6, lambda c=counter: table.accept("gcs", 1, c))  # type: ignore[misc]
        assert (wins, losses) == (1, 5)
