"""Key provisioning, sans-I/O: when a SETUP_SIGNING may go out, and when its key is enabled.

Theory of operation
-------------------
ArduPilot and PX4 take a new signing key from SETUP_SIGNING (message 256); whoever sends
one first over telemetry owns the link (ArduPilot #10311), and a ground station that
enables a key the vehicle never took locks itself out (QGroundControl #14251).  So:

* :func:`wired` -- the key goes only over a link marked wired: a serial/USB device or a
  loopback address.  Anything else is refused before a byte is sent.
* :class:`Provisioning` -- fed each frame heard on that link and the time, it answers a
  :class:`Step`.  The first HEARTBEAT of the vehicle's autopilot (``system_id``) decides:
  armed (``MAV_MODE_FLAG_SAFETY_ARMED`` in ``base_mode``) is a refusal, else SETUP_SIGNING
  is due (again every ``resend_s`` while unconfirmed: a lost datagram).  The key is
  **confirmed** only by a HEARTBEAT from that system whose signature verifies with the new
  key (one heard first too: the vehicle took it in an attempt whose confirmation was lost,
  so a retry with the same key ends that lock-out); only then is it enabled.  Past
  ``timeout_s`` without one: a refusal, and nothing is enabled (the old key stays the one
  in use: a rotation that is not confirmed changes nothing).

No socket, file or clock here: the driver (:mod:`antireplay.wiring.mavlink_keys`) reads
the link, encodes the message and writes ``signing.keys``.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
from dataclasses import dataclass
from enum import Enum

from antireplay.mavlink.codec import MAV_EPOCH, UNITS_PER_S, Frame

__all__ = [
    "Provisioning",
    "Step",
    "StepKind",
    "heartbeat_state",
    "vehicle_record",
    "verifies",
    "wired",
]

HEARTBEAT = 0
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_AUTOPILOT_INVALID = 8  # a heartbeat from a component that is not an autopilot
_SIG = 6  # the signature's bytes at the end of a signed frame


def vehicle_record(system_id: int) -> str:
    """The name of vehicle ``system_id``'s line in ``signing.keys`` (``sysid:N PASSPHRASE``:
    MAVProxy skips it, no device is named so; a router with ``--system-id N`` takes it)."""
    return f"sysid:{system_id}"


def wired(kind: str, host: str) -> bool:
    """A serial device (``kind`` of a parsed endpoint), or an address on this host
    (loopback): never a network link."""
    if kind == "serial" or host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve anywhere
        return False


def verifies(frame: Frame, key: bytes) -> bool:
    """Whether ``frame`` is signed and its signature is ``key``'s (constant time)."""
    if not frame.signed:
        return False
    expected = hashlib.sha256(key + frame.raw[:-_SIG]).digest()[:_SIG]
    return hmac.compare_digest(expected, frame.raw[-_SIG:])


def heartbeat_state(frame: Frame) -> tuple[int, bool] | None:
    """``(autopilot, armed)`` of a HEARTBEAT frame; None for any other message."""
    if frame.msgid != HEARTBEAT:
        return None
    payload = frame.payload.ljust(9, b"\0")  # MAVLink 2 trims trailing zero bytes
    return payload[5], bool(payload[6] & MAV_MODE_FLAG_SAFETY_ARMED)


class StepKind(Enum):
    WAIT = "wait"
    SEND = "send"  # encode and send SETUP_SIGNING (target, initial timestamp)
    ENABLE = "enable"  # confirmed: record the key, then stop
    REFUSE = "refuse"  # stop; nothing is enabled


@dataclass(frozen=True, slots=True)
class Step:
    kind: StepKind
    reason: str = ""
    target: tuple[int, int] = (0, 0)  # SEND: the vehicle's system and component
    timestamp: int = 0  # SEND: SETUP_SIGNING's initial_timestamp


class Provisioning:
    """One provisioning attempt of ``key`` on system ``system_id`` (module docstring)."""

    def __init__(
        self, key: bytes, system_id: int, now: float, *, timeout_s: float = 10.0,
        resend_s: float = 1.0,
    ) -> None:  # fmt: skip
        if len(key) != 32 or not any(key):
            raise ValueError("a MAVLink signing key is 32 bytes, not all zero")
        self.key, self.system_id = key, system_id
        self.deadline = now + timeout_s
        self.resend_s = resend_s
        self.target: tuple[int, int] | None = None  # set once SETUP_SIGNING is due
        self._sent_at: float | None = None
        self.done = False

    def heard(self, frame: Frame, now: float) -> Step:
        """A frame from the link at wall time ``now``."""
        if self.done:
            return Step(StepKind.WAIT)
        state = heartbeat_state(frame)
        if state is None or frame.sysid != self.system_id or state[0] == MAV_AUTOPILOT_INVALID:
            return self.tick(now)
        if verifies(frame, self.key):  # it signs with the new key: taken (perhaps before)
            self.done = True
            return Step(StepKind.ENABLE, f"system {self.system_id} signs with the new key")
        if self.target is None:
            if state[1]:
                self.done = True
                return Step(
                    StepKind.REFUSE,
                    f"system {self.system_id} is armed (HEARTBEAT base_mode): disarm it, "
                    "then provision",
                )
            self.target = (frame.sysid, frame.compid)
        return self.tick(now)

    def tick(self, now: float) -> Step:
        """The time passes: resend, give up, or wait."""
        if self.done:
            return Step(StepKind.WAIT)
        if now >= self.deadline:
            self.done = True
            heard = "no HEARTBEAT signed with the new key" if self.target else "no HEARTBEAT"
            return Step(
                StepKind.REFUSE,
                f"timed out: {heard} from system {self.system_id}; nothing enabled",
            )
        if self.target is not None and (
            self._sent_at is None or now - self._sent_at >= self.resend_s
        ):
            self._sent_at = now
            stamp = int((max(now, MAV_EPOCH) - MAV_EPOCH) * UNITS_PER_S)
            return Step(StepKind.SEND, target=self.target, timestamp=stamp)
        return Step(StepKind.WAIT)
