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


def heartbeat(
    key: bytes | None, *, armed: bool = False, system: int = 1, component: int = 1,
    stamp: int = 1, autopilot: int = dialect.MAV_AUTOPILOT_ARDUPILOTMEGA,
) -> Frame:  # fmt: skip
    out = _Out()
    mav = dialect.MAVLink(out, srcSystem=system, srcComponent=component)
    if key is not None:
        mav.signing.secret_key, mav.signing.sign_outgoing = key, True
        mav.signing.timestamp = stamp
    mode = dialect.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0
    mav.heartbeat_send(dialect.MAV_TYPE_QUADROTOR, autopilot, mode, 0, 4)
    return parse_frame(out.data)


def radio_status() -> Frame:
    out = _Out()
    dialect.MAVLink(out, srcSystem=51, srcComponent=68).radio_status_send(1, 2, 3, 4, 5, 6, 7)
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


def test_the_key_is_enabled_only_by_a_fresh_heartbeat_signed_with_it() -> None:
    attempt = Provisioning(NEW, 1, now=0.0, current=OLD, resend_s=1.0)
    assert attempt.tick(0.05).kind is StepKind.WAIT  # nothing heard yet: nothing sent
    sent = attempt.heard(heartbeat(OLD), 0.1)
    assert (sent.kind, sent.target, sent.sign_with) == (StepKind.SEND, (1, 1), OLD)
    for frame in (heartbeat(OLD), heartbeat(None), heartbeat(NEW, system=2)):
        assert attempt.heard(frame, 0.2).kind is StepKind.WAIT
    assert attempt.tick(1.2).kind is StepKind.SEND  # unconfirmed: sent again
    assert attempt.heard(heartbeat(NEW, stamp=sent.timestamp), 1.3).kind is StepKind.ENABLE


def test_a_replayed_old_heartbeat_signed_with_the_new_key_never_confirms() -> None:
    """Review 3: a capture of the vehicle signing with the new key before this run."""
    t = 1.8e9  # a wall time: initial_timestamp counts from 2015
    attempt = Provisioning(NEW, 1, now=t, current=OLD)
    sent = attempt.heard(heartbeat(OLD), t + 0.1)
    assert sent.kind is StepKind.SEND and sent.timestamp > 0
    old = heartbeat(NEW, stamp=sent.timestamp - 1)
    assert attempt.heard(old, t + 0.2).kind is StepKind.WAIT
    assert attempt.heard(heartbeat(NEW, stamp=sent.timestamp), t + 0.3).kind is StepKind.ENABLE


def test_past_the_deadline_nothing_is_enabled() -> None:
    attempt = Provisioning(NEW, 1, now=0.0, current=OLD, timeout_s=5.0)
    attempt.heard(heartbeat(OLD), 0.1)
    step = attempt.tick(5.0)
    assert step.kind is StepKind.REFUSE and "nothing enabled" in step.reason
    assert attempt.heard(heartbeat(NEW, stamp=2**40), 5.1).kind is StepKind.WAIT


def test_a_vehicle_already_on_the_new_key_is_sent_it_signed_with_it_then_confirmed() -> None:
    """A retry after a lost confirmation: SETUP_SIGNING signed with the new key, then a
    HEARTBEAT from after it confirms (never the earlier one alone)."""
    attempt = Provisioning(NEW, 1, now=0.0)
    sent = attempt.heard(heartbeat(NEW), 0.1)
    assert (sent.kind, sent.sign_with) == (StepKind.SEND, NEW)
    assert attempt.heard(heartbeat(NEW, stamp=sent.timestamp + 5), 0.2).kind is StepKind.ENABLE


def test_in_a_rotation_an_unsigned_disarmed_heartbeat_decides_nothing() -> None:
    """Review 2: a spoofed "disarmed" HEARTBEAT must not make the key go out."""
    attempt = Provisioning(NEW, 1, now=0.0, current=OLD, timeout_s=5.0)
    for frame in (heartbeat(None), heartbeat(passphrase_key("attacker"))):
        assert attempt.heard(frame, 0.1).kind is StepKind.WAIT
    step = attempt.tick(5.0)
    assert (
        step.kind is StepKind.REFUSE and "neither the file's record nor the new key" in step.reason
    )


def test_an_armed_heartbeat_after_the_send_stops_every_further_send() -> None:
    attempt = Provisioning(NEW, 1, now=0.0)
    assert attempt.heard(heartbeat(None), 0.1).kind is StepKind.SEND
    step = attempt.heard(heartbeat(None, armed=True), 0.5)
    assert step.kind is StepKind.REFUSE and "armed" in step.reason and attempt.sent
    assert attempt.tick(2.0).kind is StepKind.WAIT


@pytest.mark.parametrize(
    "frame",
    [heartbeat(None, component=154), heartbeat(None, autopilot=dialect.MAV_AUTOPILOT_INVALID)],
)
def test_only_the_autopilot_component_is_the_target(frame: Frame) -> None:
    """Review 9: a gimbal (component 154) or a non-autopilot never gets SETUP_SIGNING."""
    attempt = Provisioning(NEW, 1, now=0.0)
    assert attempt.heard(frame, 0.1).kind is StepKind.WAIT
    assert attempt.heard(heartbeat(None), 0.2).target == (1, 1)


def test_a_telemetry_radio_on_the_link_is_refused() -> None:
    attempt = Provisioning(NEW, 1, now=0.0)
    step = attempt.heard(radio_status(), 0.1)
    assert step.kind is StepKind.REFUSE and "RADIO_STATUS" in step.reason and not attempt.sent


def test_a_wrong_system_id_names_the_systems_heard() -> None:
    attempt = Provisioning(NEW, 2, now=0.0, timeout_s=1.0)
    attempt.heard(heartbeat(None, system=1), 0.1)
    assert "heard system 1" in attempt.tick(1.0).reason


def test_an_all_zero_key_is_no_key() -> None:
    with pytest.raises(ValueError, match="not all zero"):
        Provisioning(bytes(32), 1, now=0.0)
