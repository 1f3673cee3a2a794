"""The rcan SDK's ``tests/test_qos.py``, restated.  ``QoSManager`` is the sender's
machinery (ACK timers, retries); antireplay is the receiver, so its cases become what
our receive side does with what that sender sends: a retransmission (same msg_id) is
never admitted twice, a fresh duplicate ESTOP is processed and flagged, and ``qos`` is
an integer hint read only by the retry rule (the gateway answers a ``qos >= 1``
retransmission with the original answer; tests/rcan/test_retries.py)."""

from __future__ import annotations

import json

import pytest
from rcan import RCANMessage
from rcan.qos import make_estop_with_qos

from antireplay import MessageType, safety_class
from antireplay.rcan.envelope import parse
from harness import SDK_NOW, SdkReplayAdapter

TARGET = "rcan://registry.rcan.dev/acme/arm/v1/unit-001"


def sdk_message(cmd: str = "move_forward", qos: int = 0) -> dict[str, object]:
    msg = RCANMessage(cmd=cmd, target=TARGET, qos=qos, msg_id="q-1", timestamp=SDK_NOW)
    return dict(msg.to_dict())


@pytest.mark.parametrize("case", ["test_values", "test_is_int_enum"])
def test_qos_level(case: str) -> None:
    """Documented difference (no QoS enum).  The SDK names levels 0, 1, 2 in an IntEnum;
    ours reads ``qos`` as the integer it is on the wire, kept as sent."""
    for level in (0, 1, 2):
        assert parse(json.dumps(sdk_message(qos=level)).encode()).qos == level


SENDER_CASES = [
    "test_init_defaults", "test_fire_and_forget_calls_send", "test_acknowledged_success_on_ack",
    "test_acknowledged_timeout_raises", "test_exactly_once_commit_success", "test_pending_count",
    "test_record_ack_unknown_msg_id", "test_record_commit_unknown_msg_id",
]  # fmt: skip


@pytest.mark.parametrize("case", SENDER_CASES)
def test_qos_manager(case: str) -> None:
    """Documented difference (the receiver's side).  The SDK's case checks its sender's
    timers and ACK bookkeeping; ours has no sender.  What a receiver owes that sender:
    the first copy is admitted, and every retransmission of it (any qos) is refused as a
    replay here, never executed twice (the gateway answers a qos >= 1 retransmission with
    the original answer)."""
    adapter = SdkReplayAdapter()
    for qos in (0, 1, 2):
        msg = {**sdk_message(qos=qos), "msg_id": f"q-{qos}"}
        assert adapter.validate_replay(msg) == (True, "")
        allowed, reason = adapter.validate_replay(msg)
        assert (allowed, reason.split(":")[0]) == (False, "REPLAY_DETECTED")


def test_estop_timeout_raises_safety_halt() -> None:
    """Documented difference (the receiver's side).  The SDK's sender raises
    SafetyHaltError when an ESTOP goes unacknowledged; ours processes a retransmitted
    fresh ESTOP again and flags it ``REPLAY_DETECTED``: a stop whose answer was lost must
    still reach the robot."""
    adapter = SdkReplayAdapter()
    msg = sdk_message("ESTOP", qos=2)
    assert adapter.validate_replay(msg) == (True, "")
    assert adapter.validate_replay(msg) == (True, "REPLAY_DETECTED")


def test_estop_has_qos_2() -> None:
    msg = make_estop_with_qos(ruri=TARGET, reason="Test emergency stop")
    assert parse(json.dumps(msg.to_dict()).encode()).qos == 2


def test_estop_cmd() -> None:
    msg = make_estop_with_qos(ruri=TARGET, reason="Test")
    assert safety_class(parse(json.dumps(msg.to_dict()).encode())) == (MessageType.SAFETY, "ESTOP")


def test_estop_is_rcan_message() -> None:
    msg = make_estop_with_qos(ruri=TARGET, reason="Test")
    msg.timestamp = SDK_NOW
    assert SdkReplayAdapter().validate_replay(msg.to_dict()) == (True, "")


def test_command_nack_in_message_type() -> None:
    assert MessageType(18) is MessageType.COMMAND_NACK


def test_command_ack_in_message_type() -> None:
    assert MessageType(17) is MessageType.COMMAND_ACK
