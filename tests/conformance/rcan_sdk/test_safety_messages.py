"""The rcan SDK's ``tests/test_safety_messages.py``, restated: what its ``rcan.safety``
builders produce, as our vocabulary (:class:`~antireplay.MessageType`,
:class:`~antireplay.SafetyEvent`, :func:`~antireplay.safety_class`) reads it through
:class:`~harness.SdkReplayAdapter`.  We build no messages: a receiver's part is how
it classes and refuses them."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import pytest
from rcan.safety import (
    make_estop_message,
    make_resume_message,
    make_stop_message,
    make_transparency_message,
)

from antireplay import MessageType, SafetyEvent
from antireplay.rcan.envelope import parse
from harness import SdkReplayAdapter

RURI = "rcan://rcan.dev/boston-dynamics/spot/bd-spot-001a2b3c"
REASON = "Unit test safety check"
FACTORIES: list[Callable[[str, str], dict[str, Any]]] = [
    make_estop_message,
    make_stop_message,
    make_resume_message,
]


@pytest.mark.parametrize(
    ("factory", "event"),
    [(make_estop_message, "ESTOP"), (make_stop_message, "STOP"), (make_resume_message, "RESUME")],
    ids=["test_make_estop_message", "test_make_stop_message", "test_make_resume_message"],
)
def test_make_safety_message(factory: Callable[[str, str], dict[str, Any]], event: str) -> None:
    msg = factory(RURI, REASON)
    assert MessageType(msg["message_type"]) is MessageType.SAFETY
    assert SafetyEvent(msg["safety_event"]) is SafetyEvent(event)
    adapter = SdkReplayAdapter()
    assert adapter.is_safety_message(msg) is True
    assert adapter.validate_safety_message(msg) == []


def test_message_id_is_uuid4() -> None:
    """Pass, and wider: the SDK's uuid4 ids are accepted, as is any other msg_id string:
    the seen-set needs an id to be unique, not to have a format."""
    adapter = SdkReplayAdapter()
    for factory in FACTORIES:
        assert adapter.validate_safety_message(factory(RURI, REASON)) == []
    assert (
        adapter.validate_safety_message({**make_stop_message(RURI, REASON), "message_id": "s1"})
        == []
    )


def test_reason_truncated_at_512() -> None:
    """Documented difference (never alter a message).  The SDK's builder cuts a reason to
    512 characters; a receiver must not change what was signed, so ours keeps a 600-char
    reason as sent (the envelope's size limit bounds it)."""
    msg = {**make_estop_message(RURI, REASON), "reason": "x" * 600}
    assert SdkReplayAdapter().validate_safety_message(msg) == []
    env = parse(json.dumps({"msg_id": "m", "cmd": "ESTOP", "target": RURI, "timestamp": 1,
                            "params": {"reason": "x" * 600}}).encode())  # fmt: skip
    assert len(env.params["reason"]) == 600


def test_timestamp_ms_is_int() -> None:
    msg = make_estop_message(RURI, REASON)
    env = parse(json.dumps({"msg_id": "m", "cmd": "ESTOP", "target": RURI,
                            "timestamp_ms": msg["timestamp_ms"]}).encode())  # fmt: skip
    assert env.seconds == msg["timestamp_ms"] / 1000


def test_is_safety_message() -> None:
    """Documented difference (a message, not a fragment).  The SDK calls
    ``{"message_type": 6}`` a safety message; ours classes only a whole envelope (msg_id,
    timestamp, cmd, target): a fragment is refused, so it is no safety message."""
    adapter = SdkReplayAdapter()
    for fragment in ({"message_type": 6}, {"message_type": 1}, {"message_type": 0}, {}):
        assert adapter.is_safety_message(fragment) is False
    for factory in FACTORIES:
        assert adapter.is_safety_message(factory(RURI, REASON)) is True


def test_validate_safety_message_valid() -> None:
    assert SdkReplayAdapter().validate_safety_message(make_estop_message(RURI, REASON)) == []


def test_validate_safety_message_missing_reason() -> None:
    """Documented difference (safety beats formality).  The SDK requires a ``reason``;
    ours admits an ESTOP without one: a stop must never be refused for a missing note."""
    msg = make_estop_message(RURI, REASON)
    del msg["reason"]
    assert SdkReplayAdapter().validate_safety_message(msg) == []


def test_validate_safety_message_wrong_type() -> None:
    """Documented difference (the signed field decides).  The SDK refuses
    ``message_type=1`` on an ESTOP; ours classes a COMMAND whose ``cmd`` is ``ESTOP`` as
    SAFETY/ESTOP, because the SDK signs ``cmd`` but not ``type``."""
    msg = {**make_estop_message(RURI, REASON), "message_type": 1}
    adapter = SdkReplayAdapter()
    assert adapter.validate_safety_message(msg) == []
    assert adapter.is_safety_message(msg) is True


def test_validate_safety_message_invalid_event() -> None:
    msg = {**make_estop_message(RURI, REASON), "safety_event": "LAUNCH"}
    errors = SdkReplayAdapter().validate_safety_message(msg)
    assert any("safety_event" in e for e in errors)


def test_validate_safety_message_missing_ruri() -> None:
    msg = make_estop_message(RURI, REASON)
    del msg["ruri"]
    errors = SdkReplayAdapter().validate_safety_message(msg)
    assert any("target" in e for e in errors)  # the SDK's ruri is our target


def test_safety_message_type_constant() -> None:
    assert MessageType(6) is MessageType.SAFETY


@pytest.mark.parametrize(
    ("name", "value"), [("TRANSPARENCY", 16), ("SAFETY", 6), ("COMMAND", 1)],
    ids=["test_transparency_value", "test_safety_value", "test_command_value"],
)  # fmt: skip
def test_message_type_enum(name: str, value: int) -> None:
    assert MessageType[name] == value


TRANSPARENCY_CASES = [
    "test_type_is_18", "test_source_and_target_set", "test_payload_ai_system_true",
    "test_payload_operator", "test_payload_capabilities", "test_payload_model_family_default",
    "test_payload_model_family_custom", "test_payload_limitations_default_empty",
    "test_payload_limitations_custom", "test_payload_audit_enabled_default",
    "test_message_id_uuid_format", "test_passes_validate_message",
    "test_transparency_message_type_constant",
]  # fmt: skip


@pytest.mark.parametrize("case", TRANSPARENCY_CASES)
def test_make_transparency_message(case: str) -> None:
    """Documented difference (not a command).  The SDK's cases check its transparency
    builder's fields (``type`` 18, ``source``, ``payload``).  Ours builds none, and its
    receiver refuses the dict as ``INVALID_ENVELOPE`` (fields no command carries, and no
    ``cmd``); in the canonical table, which the SDK's own ``MessageType`` follows,
    TRANSPARENCY is 16 and 18 is COMMAND_NACK."""
    msg = make_transparency_message(
        source_ruri="rcan://rcan.dev/acme/arm/v1/unit-001",
        target_ruri="rcan://local/human-display",
        operator="Acme Robotics",
        capabilities=["navigation", "speech"],
    )
    allowed, reason = SdkReplayAdapter().validate_replay(msg)
    assert (allowed, reason.split(":")[0]) == (False, "INVALID_ENVELOPE")
    assert (MessageType.TRANSPARENCY, MessageType(msg["type"])) == (16, MessageType.COMMAND_NACK)
