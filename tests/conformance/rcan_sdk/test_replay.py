"""The rcan SDK's ``tests/test_replay.py``, restated: its ``ReplayCache`` cases through
:class:`~harness.SdkReplayAdapter` over our :class:`~antireplay.ReplayCache`.

Every case runs on a cache that has been up a minute: a cache that starts at "now"
refuses what is stamped before its start plus its skew (its restart fence), which
``test_safety_message_fresh_allowed`` states once."""

from __future__ import annotations

import pytest
from rcan import RCANMessage

from antireplay import ConfigError
from harness import SDK_NOW, SdkReplayAdapter

TARGET = "rcan://registry.rcan.dev/acme/arm/v1/unit-001"


def sdk_message(cmd: str = "move_forward", msg_id: str = "m-1") -> dict[str, object]:
    """The SDK's ``make_msg``: an ``RCANMessage`` as it goes on the wire, stamped now."""
    return dict(RCANMessage(cmd=cmd, target=TARGET, msg_id=msg_id, timestamp=SDK_NOW).to_dict())


# --- TestReplayCacheBasics -----------------------------------------------------------------------


def test_fresh_message_allowed() -> None:
    assert SdkReplayAdapter().check_and_record("m-1", SDK_NOW) == (True, "")


def test_duplicate_msg_id_rejected() -> None:
    cache = SdkReplayAdapter()
    assert cache.check_and_record("m-1", SDK_NOW)[0] is True
    allowed, reason = cache.check_and_record("m-1", SDK_NOW)
    assert allowed is False
    assert reason.startswith("REPLAY_DETECTED")


def test_stale_timestamp_rejected() -> None:
    allowed, reason = SdkReplayAdapter().check_and_record("m-1", SDK_NOW - 31)
    assert allowed is False
    assert reason.startswith("MESSAGE_STALE") and "31" in reason


def test_exactly_at_window_boundary_rejected() -> None:
    assert SdkReplayAdapter().check_and_record("m-1", SDK_NOW - 31)[0] is False


def test_future_timestamp_rejected() -> None:
    allowed, reason = SdkReplayAdapter().check_and_record("m-1", SDK_NOW + 10)
    assert allowed is False
    assert reason.startswith("MESSAGE_FROM_FUTURE") and "future" in reason.lower()


def test_invalid_timestamp_rejected() -> None:
    allowed, reason = SdkReplayAdapter().check_and_record("m-1", "not-a-number")
    assert allowed is False
    assert reason.startswith("INVALID_TIMESTAMP")


# --- TestSafetyWindow ----------------------------------------------------------------------------


def test_safety_message_uses_10s_window() -> None:
    allowed, reason = SdkReplayAdapter().check_and_record("m-1", SDK_NOW - 11, is_safety=True)
    assert allowed is False
    assert reason.startswith("MESSAGE_STALE")


def test_safety_message_fresh_allowed() -> None:
    """Documented difference (restart fence).  The SDK admits a safety message stamped 5 s
    ago on a cache created now; ours refuses it there (``restart_fence``): a new process
    cannot know whether its predecessor accepted that msg_id.  On a cache up longer than
    the message's age it is admitted, as the SDK expects."""
    fresh = SdkReplayAdapter(up_s=0)
    allowed, reason = fresh.check_and_record("m-1", SDK_NOW - 5, is_safety=True)
    assert allowed is False
    assert reason.endswith("(restart_fence)")
    running = SdkReplayAdapter()
    assert running.check_and_record("m-1", SDK_NOW - 5, is_safety=True) == (True, "")


def test_non_safety_11s_old_allowed() -> None:
    cache = SdkReplayAdapter()
    assert cache.check_and_record("m-1", SDK_NOW - 11, is_safety=False) == (True, "")


# --- TestCacheEviction ---------------------------------------------------------------------------


def test_overflow_evicts_oldest() -> None:
    """Documented difference (fail closed).  The SDK's full cache evicts its oldest
    msg_id and admits the newcomer; forgetting a live msg_id would re-open its replay, so
    ours stays bounded by refusing the newcomer (``MESSAGE_STALE``, ``saturated``) until
    an entry's window ends, and the oldest msg_id is still refused as a replay."""
    cache = SdkReplayAdapter(window_s=300, max_size=5)
    for i in range(5):
        assert cache.check_and_record(f"msg-{i}", SDK_NOW)[0] is True
    assert len(cache) <= 5
    allowed, reason = cache.check_and_record("msg-new", SDK_NOW)
    assert (allowed, reason.startswith("MESSAGE_STALE")) == (False, True)
    assert len(cache) <= 5
    assert cache.check_and_record("msg-0", SDK_NOW)[1].startswith("REPLAY_DETECTED")


# --- TestValidateReplay --------------------------------------------------------------------------


def test_validate_fresh_message_allowed() -> None:
    assert SdkReplayAdapter().validate_replay(sdk_message()) == (True, "")


def test_validate_duplicate_message_rejected() -> None:
    cache, msg = SdkReplayAdapter(), sdk_message()
    cache.validate_replay(msg)
    allowed, reason = cache.validate_replay(msg)
    assert allowed is False
    assert reason.startswith("REPLAY_DETECTED")


def test_estop_fresh_allowed() -> None:
    assert SdkReplayAdapter().validate_replay(sdk_message("ESTOP")) == (True, "")


def test_estop_duplicate_rejected() -> None:
    """Documented difference (safety beats availability).  The SDK drops a duplicate
    ESTOP; ours processes a *fresh* duplicate ESTOP (within its 10 s window) and flags it
    ``REPLAY_DETECTED`` for the metrics and the audit trail: replaying a stop cannot move a
    robot, while dropping a genuine retransmitted stop could leave it moving."""
    cache, msg = SdkReplayAdapter(), sdk_message("ESTOP")
    cache.validate_replay(msg)
    assert cache.validate_replay(msg) == (True, "REPLAY_DETECTED")
    cache.clock.step_wall(11)  # no longer fresh: the duplicate is refused
    assert cache.validate_replay(msg)[0] is False


# --- TestWindowConfig ----------------------------------------------------------------------------


def test_custom_window_respected() -> None:
    cache = SdkReplayAdapter(window_s=60)
    assert cache.check_and_record("m-1", SDK_NOW - 45) == (True, "")


def test_window_clamped_to_max() -> None:
    """Documented difference (no silent clamp).  The SDK turns ``window_s=9999`` into 300;
    ours refuses it with a :class:`ConfigError` naming the key and the allowed range, so a
    typo cannot silently run a window other than the one written."""
    with pytest.raises(ConfigError, match="5 to 300"):
        SdkReplayAdapter(window_s=9999)
    assert SdkReplayAdapter(window_s=300).window_s == 300


def test_window_clamped_to_min() -> None:
    """Documented difference (no silent clamp): ``window_s=1`` is a :class:`ConfigError`
    in ours, where the SDK raises it to 5."""
    with pytest.raises(ConfigError, match="5 to 300"):
        SdkReplayAdapter(window_s=1)
    assert SdkReplayAdapter(window_s=5).window_s == 5
