"""The sender source, RFC 6479 windows (WireGuard vectors) and fenced high-water tables."""

from __future__ import annotations

import itertools
import threading
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from antireplay.core.counters import (
    COUNTER_LIMIT,
    DEFAULT_WINDOW,
    FENCE,
    CounterWindow,
    FencedTable,
    NonceCounter,
    NonceTracker,
)
from antireplay.core.errors import (
    CounterExhaustedError,
    CounterReplayedError,
    CounterTooOldError,
    InvalidCounterError,
    MessageStaleError,
    NonceExhaustedError,
    ReplayAttackError,
)
from antireplay.state.ceilings import persistent_counter
from harness import assert_never_reused, kill9_runs, race, run_threads


def commits(window: CounterWindow, counter: int) -> bool:
    """Whether ``window.commit`` records ``counter`` (a refusal is a typed error)."""
    try:
        window.commit(counter)
    except ReplayAttackError:
        return False
    return True


# --- the three CleitonQ properties, ported ----------------------------------------------------


def test_eight_threads_thousand_next_are_distinct() -> None:
    counter = NonceCounter()
    values: list[list[int]] = [[] for _ in range(8)]
    run_threads(8, lambda i: values[i].extend(counter.next() for _ in range(1_000)))
    flat = [v for vs in values for v in vs]
    assert len(set(flat)) == 8_000
    assert all(a < b for vs in values for a, b in itertools.pairwise(vs))


def test_window_sequence_5_5_3_6() -> None:
    window = CounterWindow()
    assert [commits(window, n) for n in (5, 5, 3, 6)] == [True, False, True, True]
    assert window.last == 6


def test_four_threads_offering_1_to_500_give_500_commits() -> None:
    window = CounterWindow()
    committed: list[int] = []
    lock = threading.Lock()

    def offer(_: int) -> None:
        for n in range(1, 501):
            if commits(window, n):
                with lock:
                    committed.append(n)

    run_threads(4, offer)
    assert sorted(committed) == list(range(1, 501))
    assert window.last == 500


# --- the strict receiver (in-order links) ------------------------------------------------------


def test_tracker_sequence_5_5_3_6() -> None:
    tracker = NonceTracker()
    assert [tracker.accept(n) for n in (5, 5, 3, 6)] == [True, False, False, True]
    assert tracker.last_accepted() == 6


def test_four_threads_racing_to_accept_1_to_500_give_500_acceptances() -> None:
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
    assert tracker.last_accepted() == 500


def test_tracker_check_records_nothing_and_names_the_refusal() -> None:
    tracker = NonceTracker()
    tracker.check(5)
    tracker.check(5)  # still fresh: check recorded nothing
    assert tracker.last_accepted() == 0
    tracker.commit(5)
    with pytest.raises(CounterReplayedError):
        tracker.check(5)
    with pytest.raises(CounterTooOldError):
        tracker.check(3)
    with pytest.raises(InvalidCounterError):
        tracker.check(-1)
    with pytest.raises(CounterExhaustedError):
        tracker.check(COUNTER_LIMIT)
    with pytest.raises(CounterTooOldError):
        tracker.commit(4)
    assert tracker.last_accepted() == 5


def test_tracker_racing_commits_of_one_value_have_one_winner() -> None:
    tracker = NonceTracker()
    assert race(8, lambda: tracker.commit(7)) == (1, 7)
    assert tracker.last_accepted() == 7


def test_tracker_refuses_a_bad_start() -> None:
    for bad in (-1, COUNTER_LIMIT, True):
        with pytest.raises(ValueError, match="last"):
            NonceTracker(bad)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(min_value=-2, max_value=40), max_size=60))
def test_tracker_never_accepts_twice_nor_goes_backwards(offers: list[int]) -> None:
    tracker = NonceTracker()
    accepted: list[int] = []
    for n in offers:
        before = tracker.last_accepted()
        if tracker.accept(n):
            accepted.append(n)
            assert n > before
        assert tracker.last_accepted() >= before
    assert all(a < b for a, b in itertools.pairwise(accepted))
    assert tracker.last_accepted() == max(accepted, default=0)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.lists(st.integers(min_value=0, max_value=60), max_size=40), min_size=2,
                max_size=4))  # fmt: skip
def test_racing_threads_never_make_the_tracker_accept_twice(offers: list[list[int]]) -> None:
    tracker = NonceTracker()
    accepted: list[list[int]] = [[] for _ in offers]
    run_threads(len(offers), lambda i: accepted[i].extend(filter(tracker.accept, offers[i])))
    flat = [n for each in accepted for n in each]
    assert len(flat) == len(set(flat))  # no value accepted twice, across threads
    assert all(a < b for each in accepted for a, b in itertools.pairwise(each))  # no regression
    assert tracker.last_accepted() == max(flat, default=0)


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


def test_anchored_counter_follows_the_wall_and_never_repeats() -> None:
    wall = [1_000]
    counter = NonceCounter(anchor=lambda: wall[0])
    assert counter.next() == 1_000  # tied to real time
    assert counter.next() == 1_001  # the clock did not move: last + 1
    wall[0] = 500  # the wall clock stepped back
    assert counter.next() == 1_002
    wall[0] = 5_000
    assert counter.next() == 5_000


def test_anchored_persistent_counter_resumes_above_its_ceiling_and_the_wall(
    tmp_path: Path,
) -> None:
    path, wall = tmp_path / "ctr.state", [10_000]
    first = persistent_counter(path, lease=100, anchor=lambda: wall[0])
    assert first.next() == 10_000
    first.close()
    wall[0] = 0  # rebooted with a clock far behind
    assert persistent_counter(path, anchor=lambda: wall[0]).next() == 10_100


def test_restart_persists_the_new_binding_before_its_first_value(tmp_path: Path) -> None:
    counter = persistent_counter(tmp_path / "ctr.state", lease=1_000)
    counter.next()
    writes = counter.reservations
    counter.restart()
    assert counter.next() == 1
    assert counter.reservations == writes + 1


def test_counter_from_time_starts_at_the_time_it_is_given() -> None:
    """The counter reads no clock: the caller passes ``now_ns``."""
    assert NonceCounter.from_time(1_234_567).next() == 1_234_567
    assert NonceCounter.from_time(time.time_ns()).next() > 0


class BlockingCeiling:
    """A ceiling whose first claim, before it lands, has another thread restart the counter
    (``restarted``: whether that thread's call returned while the claim was in flight)."""

    counter: NonceCounter

    def __init__(self) -> None:
        self.claims: list[tuple[int, int]] = []
        self.restarted: list[bool] = []

    def claim(self, value: int, span: int) -> int:
        self.claims.append((value, span))
        if len(self.claims) == 1:
            done = threading.Event()

            def restart() -> None:
                self.counter.restart(100)
                done.set()

            threading.Thread(target=restart).start()
            self.restarted.append(done.wait(30))  # a lock held across this claim: never set
        return value

    def release(self) -> None:
        pass


def test_no_lock_is_held_while_a_ceiling_is_persisted() -> None:
    """Persist outside the lock, then believe: while one thread's reservation is being
    written another thread can restart the counter, and the reservation made for the old
    binding is not believed: the first value comes from a reservation of the new one."""
    ceiling = BlockingCeiling()
    counter = ceiling.counter = NonceCounter.on_ceiling(ceiling, 0, 10)
    assert counter.next() == 100
    assert ceiling.restarted == [True]  # restart() ran while the claim was in flight
    assert ceiling.claims == [(1, 10), (100, 10)]
    assert [counter.next() for _ in range(9)] == list(range(101, 110))
    assert counter.reservations == 2


def test_threads_past_the_ceiling_wait_for_one_reservation(tmp_path: Path) -> None:
    """Eight threads drawing from a counter with a lease of 5: every value distinct, and
    no value handed out above a ceiling before it was durable (one claim at a time)."""
    counter = persistent_counter(tmp_path / "ctr.state", lease=5)
    drawn: list[list[int]] = [[] for _ in range(8)]
    run_threads(8, lambda i: drawn[i].extend([counter.next() for _ in range(50)]))
    assert sorted(itertools.chain.from_iterable(drawn)) == list(range(1, 401))
    assert counter.reservations == 80


def test_persistent_counter_writes_once_per_lease(tmp_path: Path) -> None:
    path = tmp_path / "ctr.state"
    counter = persistent_counter(path, lease=100)
    values = [counter.next() for _ in range(1_000)]
    assert values == list(range(1, 1_001))
    assert counter.reservations == 10


def test_persistent_counter_resumes_above_ceiling(tmp_path: Path) -> None:
    path = tmp_path / "ctr.state"
    first = persistent_counter(path, lease=50)
    used = [first.next() for _ in range(7)]
    first.close()
    second = persistent_counter(path, lease=50)  # as after a crash: 43 leased values skipped
    assert second.next() > max(used)
    assert second.next() == 52


def test_persistent_counter_never_reuses_across_kill9(tmp_path: Path) -> None:
    """100 real subprocesses, each SIGKILLed at a random moment."""
    args = ["-m", "harness.workers.counter_worker", str(tmp_path / "ctr.state"), "16"]
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
        assert commits(window, counter) is expected, f"vector {number}: {counter}"


def test_wireguard_vectors_check_agrees_with_commit() -> None:
    window = CounterWindow(DEFAULT_WINDOW, limit=WG_LIMIT)
    for counter, expected in WG_VECTORS:
        try:
            window.check(counter)
            predicted = True
        except (CounterReplayedError, CounterTooOldError, CounterExhaustedError):
            predicted = False
        assert predicted is expected
        assert commits(window, counter) is expected


def _bulk(counters: list[int], tail: list[tuple[int, bool]]) -> None:
    window = CounterWindow(DEFAULT_WINDOW, limit=WG_LIMIT)
    for c in counters:
        window.commit(c)
    for c, expected in tail:
        assert commits(window, c) is expected, c


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
    window.commit(0)
    with pytest.raises(CounterReplayedError):
        window.check(0)
    with pytest.raises(CounterReplayedError):
        window.commit(0)


def test_reordering_within_window_accepted_once() -> None:
    window = CounterWindow()
    order = [5, 3, 4, 1, 2, 100, 50, 99]
    assert all(commits(window, c) for c in order)
    assert not any(commits(window, c) for c in order)


def test_check_is_typed_and_does_not_mutate() -> None:
    window = CounterWindow()
    window.check(10_000)
    assert window.last == 0
    window.commit(10_000)
    with pytest.raises(CounterTooOldError):
        window.check(10_000 - DEFAULT_WINDOW - 1)
    with pytest.raises(CounterExhaustedError):
        window.check(COUNTER_LIMIT)
    with pytest.raises(InvalidCounterError):  # not the peer's exhaustion: a malformed value
        window.check(-1)
    with pytest.raises(InvalidCounterError):
        window.commit(-1)


def test_window_race_has_one_winner() -> None:
    window = CounterWindow()
    for c in range(100):
        wins: list[int] = []

        def offer(_: int, value: int = c, w: list[int] = wins) -> None:
            if commits(window, value):
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
        if commits(window, c):
            assert c not in accepted, "a counter was accepted twice"
            assert c < COUNTER_LIMIT
            assert c > last or last - c <= DEFAULT_WINDOW
            accepted.add(c)
        else:
            assert c in accepted or c >= COUNTER_LIMIT or last - c > DEFAULT_WINDOW


# --- fenced high-water tables ---------------------------------------------------------------


def test_fenced_table_evicts_the_lowest_mark_and_raises_the_fence() -> None:
    table: FencedTable[str, list[int]] = FencedTable(3)
    for key, mark in (("a", 10), ("b", 30), ("c", 20)):
        table.commit(key, mark, list)
    table.commit("d", 40, list)  # full: "a" (mark 10) goes, the fence rises to 10
    assert (len(table), table.fence, "a" in table, table.evictions) == (3, 10, False, 1)
    with pytest.raises(MessageStaleError) as refused:
        table.check("a", 10)  # the evicted key's old values cannot come back
    assert refused.value.detail == FENCE
    with pytest.raises(MessageStaleError):
        table.commit("e", 5, list)
    assert table.check("a", 11) is None  # above the fence: a new key may start
    table.commit("e", 25, list)  # evicts "c" (20): the fence only rises
    assert table.fence == 20


def test_fenced_table_check_records_nothing() -> None:
    table: FencedTable[str, list[int]] = FencedTable(1)
    table.commit("a", 1, list)
    assert table.check("b", 10**18) is None
    assert (len(table), table.fence, table.mark("a")) == (1, -1, 1)


def test_fenced_table_marks_never_go_down_and_entries_persist() -> None:
    table: FencedTable[str, list[int]] = FencedTable(2)
    entry = table.commit("a", 5, list)
    entry.append(1)
    assert table.commit("a", 3, list) is entry
    assert table.mark("a") == 5
    table.commit("a", 9, list)
    assert (table.mark("a"), table.get("a")) == (9, [1])


def test_fenced_table_refused_newcomer_evicts_nothing() -> None:
    """A full table refuses a newcomer at or below its lowest mark *before* evicting:
    the live key stays, the fence stays (review finding 5)."""
    table: FencedTable[str, list[int]] = FencedTable(2)
    table.commit("a", 100, list)
    table.commit("b", 200, list)
    assert table.check("c", 50) is None  # above the fence: check leaves the scan to commit
    for value in (50, 100):
        with pytest.raises(MessageStaleError, match=r"lowest mark of a full table \(100\)") as no:
            table.commit("c", value, list)
        assert no.value.detail == FENCE
    assert ("a" in table, "c" in table, table.fence, len(table), table.evictions) == (
        True, False, -1, 2, 0,
    )  # fmt: skip
    table.commit("c", 101, list)  # above the lowest mark: now "a" goes, the fence rises
    assert ("a" in table, table.fence, table.evictions) == (False, 100, 1)


def test_fenced_table_discard_keeps_the_fence() -> None:
    table: FencedTable[int, list[int]] = FencedTable(2)
    table.commit(1, 1, list)
    assert table.discard(1) == []
    assert (len(table), table.fence) == (0, -1)


def test_window_commit_race_one_winner() -> None:
    window = CounterWindow()
    for counter in range(50):
        wins, losses = race(6, lambda c=counter: window.commit(c))  # type: ignore[misc]
        assert (wins, losses) == (1, 5)
