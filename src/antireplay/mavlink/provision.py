"""Key provisioning, sans-I/O: when a SETUP_SIGNING may go out, and when its key is enabled.

Theory of operation
-------------------
ArduPilot and PX4 take a new signing key from SETUP_SIGNING (message 256); whoever sends
one first over telemetry owns the link (ArduPilot #10311), and a ground station that
enables a key the vehicle never took locks itself out (QGroundControl #14251).  So:

* :func:`wired` -- the key goes only over a link marked wired: a serial/USB device or a
  loopback address.  A link that carries RADIO_STATUS (a SiK telemetry radio) is refused.
* :class:`Provisioning` -- fed each frame heard on that link and the time, it answers a
  :class:`Step`.  Only HEARTBEATs of the vehicle's autopilot (``system_id``, component 1,
  autopilot not INVALID) count.  The first one that is *authenticated* decides: signed
  with the file's ``current`` key or the new one (unsigned too when the file has no key:
  a first provisioning trusts the wire).  SETUP_SIGNING is then due, signed with the key
  that HEARTBEAT was signed with, again every ``resend_s``.  Any HEARTBEAT saying armed
  refuses, before or after a send.  The key is **confirmed** only by a HEARTBEAT signed
  with the new key whose signature timestamp is at or after this run's first
  ``initial_timestamp`` (a replayed old HEARTBEAT never confirms).  Past ``timeout_s``:
  a refusal, and nothing is enabled.

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
MAV_COMP_ID_AUTOPILOT1 = 1  # SETUP_SIGNING goes to the autopilot, never a gimbal or camera
RADIO_STATUS = 109  # injected by SiK telemetry radios: the link is not a wire
_FOREIGN = object()  # a HEARTBEAT signed with a key we do not hold
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
    SEND = "send"  # encode and send SETUP_SIGNING (target, initial timestamp, signed with)
    ENABLE = "enable"  # confirmed: record the key, then stop
    REFUSE = "refuse"  # stop; nothing is enabled


@dataclass(frozen=True, slots=True)
class Step:
    kind: StepKind
    reason: str = ""
    target: tuple[int, int] = (0, 0)  # SEND: the vehicle's system and component
    timestamp: int = 0  # SEND: SETUP_SIGNING's initial_timestamp
    sign_with: bytes | None = None  # SEND: the key the vehicle signs with now (None: unsigned)


class Provisioning:
    """One provisioning attempt of ``key`` on system ``system_id`` (module docstring);
    ``current`` is the key the file already records for it (a rotation)."""

    def __init__(
        self, key: bytes, system_id: int, now: float, *, current: bytes | None = None,
        timeout_s: float = 10.0, resend_s: float = 1.0,
    ) -> None:  # fmt: skip
        if len(key) != 32 or not any(key):
            raise ValueError("a MAVLink signing key is 32 bytes, not all zero")
        self.key, self.current, self.system_id = key, current, system_id
        self.deadline = now + timeout_s
        self.resend_s = resend_s
        self.target: tuple[int, int] | None = None  # set once SETUP_SIGNING is due
        self.sign_with: bytes | None = None
        self.first_stamp: int | None = None  # this run's first initial_timestamp
        self._sent_at: float | None = None
        self.systems: set[int] = set()  # every system heard (for the timeout's reason)
        self.foreign_key = False  # the vehicle signs with a key that is neither
        self.done = False

    @property
    def sent(self) -> bool:
        """Whether a SETUP_SIGNING has gone out (the vehicle may have taken the key)."""
        return self.first_stamp is not None

    def heard(self, frame: Frame, now: float) -> Step:
        """A frame from the link at wall time ``now``."""
        if self.done:
            return Step(StepKind.WAIT)
        if frame.msgid == RADIO_STATUS:
            return self._refuse(
                "RADIO_STATUS heard: a telemetry radio is on this link, not a wire "
                "(SETUP_SIGNING would go over the air)"
            )
        state = heartbeat_state(frame)
        if state is not None:
            self.systems.add(frame.sysid)
        autopilot = (
            state is not None
            and frame.sysid == self.system_id
            and frame.compid == MAV_COMP_ID_AUTOPILOT1
            and state[0] != MAV_AUTOPILOT_INVALID
        )
        if autopilot and (step := self._decide(frame, armed=bool(state and state[1]))):
            return step
        return self.tick(now)

    def _decide(self, frame: Frame, *, armed: bool) -> Step | None:
        """The vehicle's autopilot HEARTBEAT: refused if armed, confirmed if fresh and
        signed with the new key, else the one that sets the target if authenticated."""
        if armed:
            return self._refuse(
                f"system {self.system_id} is armed (HEARTBEAT base_mode): disarm it, then provision"
            )
        signer = self._signer(frame)
        if self.first_stamp is not None and signer == self.key:
            if frame.timestamp >= self.first_stamp:
                self.done = True
                return Step(StepKind.ENABLE, f"system {self.system_id} signs with the new key")
        elif self.target is None and signer is not _FOREIGN:
            self.target = (frame.sysid, frame.compid)
            self.sign_with = signer if isinstance(signer, bytes) else None
        return None

    def _signer(self, frame: Frame) -> bytes | object:
        """The key ``frame`` is signed with: the new one, the current one, None (unsigned,
        when there is no current key to demand), else ``_FOREIGN`` (decides nothing)."""
        for key in (self.key, self.current):
            if key is not None and verifies(frame, key):
                return key
        if frame.signed:
            self.foreign_key = True
        return None if self.current is None and not frame.signed else _FOREIGN

    def _refuse(self, reason: str) -> Step:
        self.done = True
        return Step(StepKind.REFUSE, reason)

    def tick(self, now: float) -> Step:
        """The time passes: resend, give up, or wait."""
        if self.done:
            return Step(StepKind.WAIT)
        if now >= self.deadline:
            return self._refuse(f"timed out: {self._missing()}; nothing enabled")
        if self.target is not None and (
            self._sent_at is None or now - self._sent_at >= self.resend_s
        ):
            self._sent_at = now
            stamp = int((max(now, MAV_EPOCH) - MAV_EPOCH) * UNITS_PER_S)
            if self.first_stamp is None:
                self.first_stamp = stamp
            return Step(StepKind.SEND, target=self.target, timestamp=stamp,
                        sign_with=self.sign_with)  # fmt: skip
        return Step(StepKind.WAIT)

    def _missing(self) -> str:
        """What never came, said so the operator can act."""
        system = f"system {self.system_id}"
        if self.target is not None:
            return f"no fresh HEARTBEAT signed with the new key from {system}"
        if self.foreign_key:
            return f"{system} signs with a key that is neither the file's record nor the new key"
        if self.system_id not in self.systems and self.systems:
            heard = ", ".join(str(s) for s in sorted(self.systems))
            return f"no HEARTBEAT from {system} (heard system {heard}: --system-id?)"
        return f"no HEARTBEAT from {system}'s autopilot"
