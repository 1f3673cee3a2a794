"""Every §8.3 rule of the freshness window, and the RCAN SDK's failures as regressions."""

from __future__ import annotations

import contextlib
import gc
import math
from collections.abc import Callable

import pytest

from antireplay import (
    Code,
    ConfigError,
    InvalidMessageIdError,
    InvalidTimestampError,
    ManualClock,
    MessageFromFutureError,
    MessageStaleError,
    MessageType,
    ReplayAttackError,
    ReplayCache,
    ReplayDetectedError,
)
from antireplay.state.memory import MemoryStore
from harness import race


def memory(cache: ReplayCache) -> MemoryStore:
    assert isinstance(cache.store, MemoryStore)
    return cache.store


def purge(cache: ReplayCache) -> int:
    """Run the memory backend's full purge on the cache's clock."""
    return memory(cache).purge(cache.clock.wall())


def watermark(cache: ReplayCache) -> float:
    return memory(cache).watermark()


SAFETY = MessageType.SAFETY


@pytest.fixture
def cache(impl: Callable[..., ReplayCache], clock: ManualClock) -> ReplayCache:
    return impl(window_s=30, max_size=10_000, skew_s=5.0, clock=clock)


# --- freshness --------------------------------------------------------------------------------


def test_fresh_unique_message_is_accepted(cache: ReplayCache, clock: ManualClock) -> None:
    verdict = cache.commit("m1", clock.wall())
    assert verdict.warning is None
    assert verdict.expires_at == clock.wall() + 30


def test_stale_boundary_is_exact(cache: ReplayCache, clock: ManualClock) -> None:
    now = clock.wall()
    cache.commit("edge", now - 30)  # age == window: still fresh
    with pytest.raises(MessageStaleError) as err:
        cache.commit("past-edge", now - 30.001)
    assert err.value.code is Code.MESSAGE_STALE
    assert err.value.http_status == 408


def test_future_beyond_skew_rejected(cache: ReplayCache, clock: ManualClock) -> None:
    now = clock.wall()
    cache.commit("ahead-ok", now + 5)
    with pytest.raises(MessageFromFutureError):
        cache.commit("ahead-bad", now + 5.001)


def test_duplicate_is_replay_with_409(cache: ReplayCache, clock: ManualClock) -> None:
    cache.commit("m1", clock.wall())
    with pytest.raises(ReplayDetectedError) as err:
        cache.commit("m1", clock.wall())
    assert err.value.http_status == 409
    assert err.value.to_nack("m1")["type"] == 18
    assert err.value.to_nack("m1", nack_type=31)["code"] == "REPLAY_DETECTED"


def test_safety_window_is_ten_seconds(cache: ReplayCache, clock: ManualClock) -> None:
    now = clock.wall()
    cache.commit("s-ok", now - 10, SAFETY, "STOP")
    with pytest.raises(MessageStaleError):
        cache.commit("s-old", now - 10.5, SAFETY, "STOP")
    cache.commit("c-ok", now - 10.5, MessageType.COMMAND)


def test_safety_window_never_exceeds_configured_window(
    impl: Callable[..., ReplayCache], clock: ManualClock
) -> None:
    cache = impl(window_s=5, clock=clock)
    assert cache.window_for(SAFETY) == 5
    with pytest.raises(MessageStaleError):
        cache.commit("s", clock.wall() - 6, SAFETY)


def test_entry_lives_until_its_timestamp_plus_window(
    cache: ReplayCache, clock: ManualClock
) -> None:
    ts = clock.wall() + 4
    cache.commit("future-stamped", ts)
    clock.advance(34)  # receipt + 34 s, but ts + 30 == now: still fresh, so still remembered
    purge(cache)
    with pytest.raises(ReplayDetectedError):
        cache.commit("future-stamped", ts)
    clock.advance(0.01)
    with pytest.raises(MessageStaleError):
        cache.commit("future-stamped", ts)


def test_entries_are_forgotten_after_expiry(cache: ReplayCache, clock: ManualClock) -> None:
    for i in range(100):
        cache.commit(f"m{i}", clock.wall())
    clock.advance(31)
    assert purge(cache) == 100
    assert len(cache) == 0


def test_same_id_with_new_timestamp_after_expiry_is_a_new_message(
    cache: ReplayCache, clock: ManualClock
) -> None:
    cache.commit("reused", clock.wall())
    clock.advance(31)
    cache.commit("reused", clock.wall())
    with pytest.raises(ReplayDetectedError):
        cache.commit("reused", clock.wall())


def test_precheck_records_nothing(cache: ReplayCache, clock: ManualClock) -> None:
    cache.check("p", clock.wall())
    cache.check("p", clock.wall())
    assert len(cache) == 0
    cache.commit("p", clock.wall())
    with pytest.raises(ReplayDetectedError):
        cache.check("p", clock.wall())


# --- ESTOP invariant ------------------------------------------------------------------------


def test_fresh_duplicate_estop_is_accepted_with_warning(
    cache: ReplayCache, clock: ManualClock
) -> None:
    first = cache.commit("e", clock.wall(), SAFETY, "ESTOP")
    second = cache.commit("e", clock.wall(), SAFETY, "ESTOP")
    assert first.warning is None
    assert second.warning == "REPLAY_DETECTED"


def test_later_duplicate_estop_extends_the_entry_past_its_first_expiry(
    cache: ReplayCache, clock: ManualClock
) -> None:
    t0 = clock.wall()
    cache.commit("e", t0, SAFETY, "ESTOP")  # entry expires at t0 + 10
    clock.advance(5)
    cache.commit("e", t0 + 5, SAFETY, "ESTOP")  # duplicate: entry now expires at t0 + 15
    clock.advance(6)
    assert purge(cache) == 0  # the t0 + 10 slot held only the superseded filing
    with pytest.raises(ReplayDetectedError):
        cache.commit("e", t0 + 5, SAFETY, "STOP")  # same id, still within t0 + 15
    clock.advance(5)
    assert purge(cache) == 1
    assert len(cache) == 0


def test_stale_estop_is_rejected(cache: ReplayCache, clock: ManualClock) -> None:
    with pytest.raises(MessageStaleError):
        cache.commit("e-old", clock.wall() - 10.5, SAFETY, "ESTOP")


@pytest.mark.parametrize("event", ["RESUME", "STOP", None])
def test_other_safety_events_get_no_exemption(
    cache: ReplayCache, clock: ManualClock, event: str | None
) -> None:
    cache.commit("x", clock.wall(), SAFETY, event)
    with pytest.raises(ReplayDetectedError):
        cache.commit("x", clock.wall(), SAFETY, event)


def test_estop_flag_on_command_type_gets_no_exemption(
    cache: ReplayCache, clock: ManualClock
) -> None:
    cache.commit("c", clock.wall(), MessageType.COMMAND, "ESTOP")
    with pytest.raises(ReplayDetectedError):
        cache.commit("c", clock.wall(), MessageType.COMMAND, "ESTOP")


# --- input validation -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "bad",
    [
        math.nan,
        math.inf,
        -math.inf,
        True,
        False,
        None,
        -1,
        -0.5,
        "nan",
        "NaN",
        "inf",
        "-1",
        "1e9",
        " 1700000000",
        "",
        "abc",
        "2026-11-23T16:00:00Z",
        [1],
        {"t": 1},
        b"1700000000",
        1_800_000_000_000,  # milliseconds in a seconds field
    ],
)
def test_invalid_timestamps_are_typed_400(cache: ReplayCache, bad: object) -> None:
    with pytest.raises(InvalidTimestampError) as err:
        cache.commit("m", bad)
    assert err.value.http_status == 400
    assert len(cache) == 0


def test_iso8601_rejection_says_why(cache: ReplayCache) -> None:
    with pytest.raises(InvalidTimestampError, match="ISO-8601"):
        cache.commit("m", "2026-11-23T16:00:00Z")


def test_decimal_string_and_int_timestamps_are_accepted(
    cache: ReplayCache, clock: ManualClock
) -> None:
    now = clock.wall()
    assert cache.commit("s", f"{now:.3f}").timestamp == now
    assert cache.commit("i", int(now)).timestamp == int(now)


@pytest.mark.parametrize("bad", ["", "x" * 129, None, 7, b"id", ["a"]])
def test_invalid_msg_ids_are_typed_400(cache: ReplayCache, clock: ManualClock, bad: object) -> None:
    with pytest.raises(InvalidMessageIdError) as err:
        cache.commit(bad, clock.wall())
    assert err.value.http_status == 400


def test_msg_id_of_128_chars_is_fine(cache: ReplayCache, clock: ManualClock) -> None:
    cache.commit("x" * 128, clock.wall())


# --- bounded memory -------------------------------------------------------------------------


def test_flood_never_reopens_replay(impl: Callable[..., ReplayCache], clock: ManualClock) -> None:
    cache = impl(window_s=30, max_size=100, clock=clock)
    victim_ts = clock.wall()
    cache.commit("victim", victim_ts)
    refused = 0
    for i in range(10_000):
        try:
            cache.commit(f"flood-{i}", clock.wall() + (i % 6))
        except MessageStaleError as exc:
            assert exc.detail in {"watermark", "saturated"}
            refused += 1
    assert len(cache) <= 100
    assert refused > 0
    assert memory(cache).evictions > 0
    with pytest.raises(ReplayAttackError) as err:
        cache.commit("victim", victim_ts)
    assert err.value.code in {Code.REPLAY_DETECTED, Code.MESSAGE_STALE}


def test_saturation_drops_soonest_expiring_entry(
    impl: Callable[..., ReplayCache], clock: ManualClock
) -> None:
    cache = impl(window_s=30, max_size=2, clock=clock)
    now = clock.wall()
    cache.commit("late", now + 3)
    cache.commit("early", now - 3)
    cache.commit("new", now)  # evicts "early" (expires soonest), watermark = now + 27
    assert watermark(cache) == now + 27
    with pytest.raises(MessageStaleError):
        cache.commit("early", now - 3)
    with pytest.raises(ReplayDetectedError):
        cache.commit("late", now + 3)
    with pytest.raises(MessageStaleError, match="saturated"):
        cache.commit("too-early", now - 2)  # would expire before every live entry


def test_fresh_estop_passes_even_when_saturated(
    impl: Callable[..., ReplayCache], clock: ManualClock
) -> None:
    cache = impl(window_s=30, max_size=5, clock=clock)
    for i in range(50):
        with contextlib.suppress(MessageStaleError):
            cache.commit(f"f{i}", clock.wall() + 5)
    with pytest.raises(MessageStaleError):
        cache.commit("cmd", clock.wall(), MessageType.COMMAND)  # saturated: commands fail closed
    assert cache.commit("estop", clock.wall(), SAFETY, "ESTOP").warning is None
    assert cache.commit("estop", clock.wall(), SAFETY, "ESTOP").warning == "REPLAY_DETECTED"
    assert len(cache) == 5


def test_purge_work_is_bounded_per_check(cache: ReplayCache, clock: ManualClock) -> None:
    for i in range(1_000):
        cache.commit(f"m{i}", clock.wall())
    clock.advance(60)
    cache.commit("next", clock.wall())
    assert len(cache) == 1_000 - 64 + 1


def test_entries_are_invisible_to_the_garbage_collector(
    cache: ReplayCache, clock: ManualClock
) -> None:
    # A full collection walks every tracked container's items; if the table's entries
    # lived in tracked containers, a 1,000,000-entry cache would add ~30 ms to each.
    for i in range(2_000):
        clock.advance(0.01)  # spread the entries over many expiry slots
        cache.commit(f"m{i}", clock.wall())
    assert len(memory(cache)._slots) > 100
    assert not gc.is_tracked(memory(cache)._expiry)
    assert not any(gc.is_tracked(slot) for slot in memory(cache)._slots.values())


# --- clock steps ----------------------------------------------------------------------------


def test_wall_clock_step_back_never_reopens_replay(cache: ReplayCache, clock: ManualClock) -> None:
    ts = clock.wall()
    cache.commit("m", ts)
    clock.advance(31)
    purge(cache)
    assert len(cache) == 0
    clock.step_wall(-20)  # NTP pulls the clock back: the capture looks fresh again
    with pytest.raises(MessageStaleError) as err:
        cache.commit("m", ts)
    assert err.value.detail == "watermark"


# --- concurrency ----------------------------------------------------------------------------


def test_threads_racing_on_one_msg_id_give_exactly_one_acceptance(
    impl: Callable[..., ReplayCache], clock: ManualClock
) -> None:
    cache = impl(clock=clock)
    for round_no in range(200):
        mid = f"race-{round_no}"
        wins, losses = race(8, lambda mid=mid: cache.commit(mid, clock.wall()))  # type: ignore[misc]
        assert (wins, losses) == (1, 7), f"round {round_no}"


# --- constructor values (no clamping; the YAML side is tests/test_config.py) --------------


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"window_s": 1000}, "replay_window_s"),
        ({"window_s": 4}, "replay_window_s"),
        ({"window_s": math.nan}, "replay_window_s"),
        ({"max_size": 0}, "msg_id_cache_size"),
        ({"max_size": 2.5}, "max_size"),
        ({"skew_s": -1}, "skew_s"),
        ({"window_s": True}, "window_s"),
    ],
)
def test_bad_constructor_values_raise_config_error(
    impl: Callable[..., ReplayCache], kwargs: dict[str, object], key: str
) -> None:
    with pytest.raises(ConfigError) as err:
        impl(**kwargs)
    assert key in err.value.key


# --- the RCAN SDK 3.7.0 failures, as regressions --------------------------------------------


def test_regression_safety_message_does_not_expire_command_entries(
    cache: ReplayCache, clock: ManualClock
) -> None:
    ts = clock.wall()
    cache.commit("cmd", ts)
    clock.advance(5)
    cache.commit("stop", clock.wall(), SAFETY, "STOP")
    clock.advance(10)  # command is 15 s old: past the safety window, inside its own
    cache.commit("stop-2", clock.wall(), SAFETY, "STOP")
    with pytest.raises(ReplayDetectedError):
        cache.commit("cmd", ts)


def test_regression_flood_of_unique_ids_does_not_evict_live_entry(
    impl: Callable[..., ReplayCache], clock: ManualClock
) -> None:
    cache = impl(window_s=30, max_size=1_000, clock=clock)
    cache.commit("victim", clock.wall())
    for i in range(1_500):
        with contextlib.suppress(MessageStaleError):
            cache.commit(f"u{i}", clock.wall() + 1)
    with pytest.raises(ReplayAttackError):
        cache.commit("victim", clock.wall())


def test_regression_nan_string_rejected(cache: ReplayCache) -> None:
    with pytest.raises(InvalidTimestampError):
        cache.commit("m", "nan")
