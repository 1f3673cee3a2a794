"""The envelope: every hostile byte string is a typed error, never an exception; the RCAN
SDK's signed subset is exactly what the SDK signs."""

from __future__ import annotations

import json
from typing import Any

import msgspec
import pytest
from rcan import RCANMessage
from rcan.signing import _canonical_message_bytes

from antireplay.core.errors import Code, InvalidEnvelopeError, InvalidTimestampError, WarningCode
from antireplay.core.messages import SafetyEvent
from antireplay.rcan.envelope import (
    MAX_INT_TIMESTAMP,
    SDK_SIGNED_FIELDS,
    encode,
    parse,
    safety_class,
)
from harness.envelopes import MITM_FIELDS

BASE = b'{"msg_id":"m","cmd":"c","target":"t","rcan":"3.2",'


@pytest.mark.parametrize("member", [*Code, *WarningCode, *SafetyEvent], ids=str)
def test_wire_enums_print_and_encode_as_their_value(
    member: Code | WarningCode | SafetyEvent,
) -> None:
    """Codes and events go into f-strings, logs and JSON: on every supported Python the
    text is the value alone (a plain ``(str, Enum)`` prints ``Code.REPLAY_DETECTED``)."""
    assert str(member) == f"{member}" == format(member, "") == member.value
    assert f"{member:>40}" == f"{member.value:>40}"
    assert json.dumps(member) == json.dumps(member.value)
    assert member == member.value


@pytest.mark.parametrize(
    "tail",
    [b'"timestamp":1,"params":{"k":"\xff"}}', b'"timestamp":1,"cmd":"\xc3"}',
     b'"timestamp":1,"params":{"\xfe":1}}'],
)  # fmt: skip
def test_bytes_that_are_not_utf8_are_invalid_envelope(tail: bytes) -> None:
    with pytest.raises(InvalidEnvelopeError, match="not UTF-8"):
        parse(BASE + tail)


def test_sig_that_is_not_utf8_is_invalid_envelope_when_read() -> None:
    env = parse(BASE + b'"timestamp":1,"sig":{"alg":"ed25519","kid":"\xff","value":"AA"}}')
    with pytest.raises(InvalidEnvelopeError, match="sig: not UTF-8"):
        env.signature()


@pytest.mark.parametrize("field", [b"timestamp", b"timestamp_ms"])
def test_integer_timestamps_beyond_64_bits_are_invalid_timestamp(field: bytes) -> None:
    at_limit = parse(BASE + b'"' + field + b'":' + str(MAX_INT_TIMESTAMP).encode() + b"}")
    assert at_limit.seconds is not None  # converts: the window judges its value
    for huge in (MAX_INT_TIMESTAMP + 1, -MAX_INT_TIMESTAMP - 1, 10**400):
        with pytest.raises(InvalidTimestampError, match="out of range"):
            parse(BASE + b'"' + field + b'":' + str(huge).encode() + b"}")


@pytest.mark.parametrize("field", ["type", "qos", "sequence_number", "loa"])
def test_integer_fields_fit_64_bits(field: str) -> None:
    parse(BASE + f'"timestamp":1,"{field}":{2**63 - 1}}}'.encode())
    with pytest.raises(InvalidEnvelopeError, match="schema"):
        parse(BASE + f'"timestamp":1,"{field}":{2**63}}}'.encode())


def test_forwarded_sig_is_re_encoded_not_copied() -> None:
    """Duplicate keys and odd spacing inside ``sig`` never reach the upstream."""
    raw = BASE + b'"timestamp":1,"sig":{ "alg":"ed25519","kid":"k","value":"BAD","value":"AA"}}'
    forwarded = encode(parse(raw))
    assert forwarded.count(b'"value"') == 1
    assert json.loads(forwarded)["sig"] == {"alg": "ed25519", "kid": "k", "value": "AA"}
    assert msgspec.json.decode(forwarded)["sig"]["value"] == "AA"


def test_sdk_signed_fields_are_what_the_sdk_signs() -> None:
    """Ask the installed SDK which attributes its canonical bytes read: exactly ours."""
    probe = RCANMessage(cmd="c", target="rcan://registry.rcan.dev/acme/arm/v2/unit-001")
    covered = set(json.loads(_canonical_message_bytes(probe)))
    assert covered == SDK_SIGNED_FIELDS
    # Changing any other field leaves the SDK's signed bytes unchanged: they are unsigned.
    before = _canonical_message_bytes(probe)
    for name, value in MITM_FIELDS.items():
        setattr(probe, name, value)
    assert _canonical_message_bytes(probe) == before


@pytest.mark.parametrize(
    ("fields", "expected"),
    [
        ({"cmd": "ESTOP"}, (6, "ESTOP")),
        ({"cmd": "STOP", "type": 1}, (6, "STOP")),
        ({"cmd": "RESUME", "type": 6}, (6, "RESUME")),
        ({"cmd": "ESTOP", "type": 6, "safety_event": "ESTOP"}, (6, "ESTOP")),
        ({"cmd": "ESTOP", "params": {"safety_event": "ESTOP"}}, (6, "ESTOP")),
        ({"cmd": "estop"}, (1, None)),  # exact, upper case: anything else is a command
        ({"cmd": "halt", "type": 6, "safety_event": "ESTOP"}, (6, "ESTOP")),
        ({"cmd": "ESTOP", "type": 3}, (3, None)),  # only COMMAND and SAFETY are mapped
    ],
)
def test_safety_class_derives_safety_from_the_signed_cmd(
    fields: dict[str, Any], expected: tuple[int, str | None]
) -> None:
    body = {"msg_id": "m", "target": "t", "timestamp": 1, **fields}
    assert safety_class(parse(json.dumps(body).encode())) == expected


@pytest.mark.parametrize(
    "fields",
    [
        {"cmd": "ESTOP", "type": 6, "safety_event": "STOP"},
        {"cmd": "STOP", "safety_event": "ESTOP"},
        {"cmd": "RESUME", "params": {"safety_event": "ESTOP"}},
    ],
)
def test_a_safety_cmd_and_a_contradicting_event_are_refused(fields: dict[str, Any]) -> None:
    body = json.dumps({"msg_id": "m", "target": "t", "timestamp": 1, **fields}).encode()
    with pytest.raises(InvalidEnvelopeError, match="contradicts"):
        parse(body)


@pytest.mark.parametrize(
    ("fields", "reason"),
    [
        ({"cmd": "launch", "type": 6, "safety_event": "LAUNCH"}, "must be one of"),
        ({"cmd": "halt", "type": 6, "safety_event": "estop"}, "must be one of"),
        ({"cmd": "halt", "safety_event": "ESTOP"}, "only a SAFETY"),
        ({"cmd": "halt", "type": 1, "safety_event": "STOP"}, "only a SAFETY"),
        ({"cmd": "ESTOP", "type": 3, "safety_event": "ESTOP"}, "only a SAFETY"),
    ],
)
def test_safety_event_is_a_known_event_on_a_safety_message_only(
    fields: dict[str, Any], reason: str
) -> None:
    body = json.dumps({"msg_id": "m", "target": "t", "timestamp": 1, **fields}).encode()
    with pytest.raises(InvalidEnvelopeError, match=reason):
        parse(body)


@pytest.mark.parametrize(
    "fields",
    [
        {"cmd": "halt", "type": 6, "safety_event": "ESTOP"},
        {"cmd": "resume", "type": 6, "safety_event": "RESUME"},
        {"cmd": "ESTOP", "safety_event": "ESTOP"},  # a signed safety cmd is SAFETY
        {"cmd": "STOP", "type": 6, "safety_event": "STOP"},
    ],
)
def test_safety_event_on_a_safety_message_parses(fields: dict[str, Any]) -> None:
    body = json.dumps({"msg_id": "m", "target": "t", "timestamp": 1, **fields}).encode()
    assert safety_class(parse(body)) == (6, fields["safety_event"])
