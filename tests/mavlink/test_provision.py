"""Provisioning decisions from values and a time: wired links only, never while armed, enabled
only when the vehicle signs with the new key, nothing enabled past the deadline."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.mavlink import Frame, parse_frame, passphrase_key
from antireplay.mavlink.provision import Provisioning, StepKind, wired

NEW, OLD = passphrase_key("new-key"), passphrase_key("old-key")


class _Out:
    def __init__(self) -> None:
        self.data = b""

    def write(self, data: bytes) -> None:
        self.data += bytes(data)


def heartbeat(key: bytes | None, *, armed: bool = False, system: int = 1) -> Frame:
    out = _Out()
    mav = dialect.MAVLink(out, srcSystem=system, srcComponent=1)
    if key is not None:
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.timestamp = key, True, 1
    mode = dialect.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0
    mav.heartbeat_send(dialect.MAV_TYPE_QUADROTOR, dialect.MAV_AUTOPILOT_ARDUPILOTMEGA, mode, 0, 4)
    return parse_frame(out.data)


@pytest.mark.parametrize(
    ("kind", "host", "expected"),
    [("serial", "/dev/ttyACM0", True), ("udpin", "127.0.0.1", True), ("tcp", "::1", True),
     ("udpin", "localhost", True), ("udpin", "0.0.0.0", False), ("udpin", "192.0.2.7", False),
     ("tcp", "vehicle.example", False), ("tcpin", "10.0.0.1", False)],
)  # fmt: skip
def test_only_a_serial_device_or_a_loopback_address_is_wired(
    kind: str, host: str, expected: bool
) -> None:
    assert wired(kind, host) is expected


def test_an_armed_vehicle_is_refused_before_anything_is_sent() -> None:
    attempt = Provisioning(NEW, 1, now=0.0)
    step = attempt.heard(heartbeat(OLD, armed=True), 0.1)
    assert step.kind is StepKind.REFUSE and "armed" in step.reason
    assert attempt.tick(0.2).kind is StepKind.WAIT  # and it stays refused


def test_the_key_is_enabled_only_by_a_heartbeat_signed_with_it() -> None:
    attempt = Provisioning(NEW, 1, now=0.0, resend_s=1.0)
    assert attempt.tick(0.05).kind is StepKind.WAIT  # nothing heard yet: nothing sent
    sent = attempt.heard(heartbeat(OLD), 0.1)
    assert (sent.kind, sent.target) == (StepKind.SEND, (1, 1))
    for frame in (heartbeat(OLD), heartbeat(None), heartbeat(NEW, system=2)):
        assert attempt.heard(frame, 0.2).kind is StepKind.WAIT
    assert attempt.tick(1.2).kind is StepKind.SEND  # unconfirmed: sent again
    assert attempt.heard(heartbeat(NEW), 1.3).kind is StepKind.ENABLE


def test_past_the_deadline_nothing_is_enabled() -> None:
    attempt = Provisioning(NEW, 1, now=0.0, timeout_s=5.0)
    attempt.heard(heartbeat(OLD), 0.1)
    step = attempt.tick(5.0)
    assert step.kind is StepKind.REFUSE and "nothing enabled" in step.reason
    assert attempt.heard(heartbeat(NEW), 5.1).kind is StepKind.WAIT


def test_a_vehicle_that_already_signs_with_the_new_key_is_confirmed() -> None:
    """A retry after a lost confirmation: the vehicle took the key, so nothing is sent."""
    attempt = Provisioning(NEW, 1, now=0.0)
    assert attempt.heard(heartbeat(NEW), 0.1).kind is StepKind.ENABLE


def test_an_all_zero_key_is_no_key() -> None:
    with pytest.raises(ValueError, match="not all zero"):
        Provisioning(bytes(32), 1, now=0.0)
