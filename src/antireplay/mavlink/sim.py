"""A simulated signing vehicle: what the MAVLink guides run when no flight controller is at hand.

It speaks MAVLink 2 with signing, as a flight controller with a key does: every frame it
sends is signed with a wall-anchored, strictly increasing timestamp
(:class:`~antireplay.mavlink.signer.TimestampSource`, the router's own sender source), so
the router's vehicle guard accepts it as it would a real autopilot's.  It sends HEARTBEAT
and ATTITUDE at a few hertz, and answers each COMMAND_LONG that verifies with a
COMMAND_ACK addressed to its sender.  Frames that do not verify (unsigned, another key, a
replayed timestamp: pymavlink's own signing checks) are counted and ignored.

**SETUP_SIGNING as ArduPilot's ``GCS_Signing.cpp`` handles it** (read at commits 006b972
and 5353d03): the key and ``initial_timestamp`` are stored and used at once, and a key of
all zeros *with* a zero timestamp turns signing off.  The timestamp then only rises: the
sim's is wall-anchored, as ArduPilot's is once ``update_signing_timestamp`` has GPS time,
so it signs with ``max(initial_timestamp, its own)``.  Differences, on purpose: those
ArduPilot versions have **no armed check** in ``handle_setup_signing`` (the issue asks for
the refusal, so the sim ignores SETUP_SIGNING while armed: ``--armed`` or a verified
MAV_CMD_COMPONENT_ARM_DISARM), and they accept unsigned frames on channel 0 (USB) while
the sim, once keyed, takes only frames signed with its key.  Without a key (never
provisioned) the sim signs nothing and takes every frame.  ``HEARTBEAT.base_mode`` says
whether it is armed.

Two transports: UDP (it sends to ``HOST:PORT``, the router's ``--vehicle udpin:HOST:PORT``,
and hears the answers on its own port) or a pseudo-terminal (the router opens its path as
a serial ``--vehicle PATH,115200``).  :meth:`SimVehicle.run` loops until its stop event is
set; :attr:`SimVehicle.counts` says what it did.
"""

from __future__ import annotations

import math
import os
import select
import socket
import threading
import time
import tty
from collections import Counter
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.core.clock import Clock
from antireplay.mavlink.signer import TimestampSource

__all__ = ["DEFAULT_UDP", "SimVehicle"]

#: Where the simulated vehicle sends by default: the router's ``--vehicle udpin:127.0.0.1:14555``.
DEFAULT_UDP = ("127.0.0.1", 14555)


class _Out:
    """pymavlink's output file: each encoded frame goes straight to the transport."""

    def __init__(self, send: Any) -> None:
        self.send = send

    def write(self, data: bytes) -> None:
        self.send(bytes(data))


class SimVehicle:
    """One simulated autopilot (module docstring); ``udp`` or ``pty``, not both."""

    def __init__(
        self,
        key: bytes | None,
        *,
        system_id: int = 1,
        udp: tuple[str, int] | None = None,
        pty: bool = False,
        rate_hz: float = 4.0,
        clock: Clock | None = None,
        armed: bool = False,
    ) -> None:
        if key is not None and len(key) != 32:
            raise ValueError("a MAVLink signing key is 32 bytes")
        self.armed = armed
        self.counts: Counter[str] = Counter()
        self.rate_hz = rate_hz
        self.timestamps = TimestampSource(clock)
        self._sock: socket.socket | None = None
        self._master: int | None = None
        self.pty_path: str | None = None
        self._to = udp or DEFAULT_UDP
        if pty:
            self._master, slave = os.openpty()
            tty.setraw(slave)
            self.pty_path = os.ttyname(slave)
            self._slave = slave
        else:
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.bind((self._to[0], 0))
        self.mav = dialect.MAVLink(_Out(self._send), srcSystem=system_id, srcComponent=1)
        self.mav.signing.link_id = 0
        self.mav.signing.timestamp = self.timestamps.next()
        self._use_key(key)
        self._started = time.monotonic()

    @property
    def key(self) -> bytes | None:
        """The key the simulator signs and verifies with (None: signing is off)."""
        key: bytes | None = self.mav.signing.secret_key
        return key

    def _use_key(self, key: bytes | None) -> None:
        self.mav.signing.secret_key = key
        self.mav.signing.sign_outgoing = key is not None

    @property
    def where(self) -> str:
        """What the router's ``--vehicle`` option should name."""
        if self.pty_path is not None:
            return f"{self.pty_path},115200"
        return f"udpin:{self._to[0]}:{self._to[1]}"

    def _send(self, data: bytes) -> None:
        if self._sock is not None:
            self._sock.sendto(data, self._to)
        elif self._master is not None:
            os.write(self._master, data)

    def _stamp(self) -> None:
        """Before each frame: the wall-anchored timestamp (pymavlink only adds one per frame)."""
        self.mav.signing.timestamp = max(self.mav.signing.timestamp, self.timestamps.next())

    def telemetry(self) -> None:
        """One HEARTBEAT and one ATTITUDE (a slow roll, so a ground station sees it move)."""
        boot_ms = int((time.monotonic() - self._started) * 1000) % 2**32
        self._stamp()
        armed = dialect.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
        self.mav.heartbeat_send(
            dialect.MAV_TYPE_QUADROTOR, dialect.MAV_AUTOPILOT_ARDUPILOTMEGA, armed, 0, 4
        )
        self._stamp()
        roll = 0.2 * math.sin(boot_ms / 1000)
        self.mav.attitude_send(boot_ms, roll, 0.0, 0.0, 0.0, 0.0, 0.0)
        self.counts["heartbeat"] += 1
        self.counts["attitude"] += 1

    def handle(self, data: bytes) -> None:
        """Frames from the router: answer each verified COMMAND_LONG, count the rest."""
        try:
            messages = self.mav.parse_buffer(data) or []
        except dialect.MAVError:  # an unsigned frame or another key's: pymavlink raises
            self.counts["refused"] += 1
            return
        for message in messages:
            kind = message.get_type()
            if kind == "BAD_DATA":
                self.counts["refused"] += 1
            elif kind == "SETUP_SIGNING":
                self._setup_signing(message)
            elif kind == "COMMAND_LONG":
                self.counts["command"] += 1
                if message.command == dialect.MAV_CMD_COMPONENT_ARM_DISARM:
                    self.armed = message.param1 == 1
                self._stamp()
                self.mav.command_ack_send(
                    message.command, dialect.MAV_RESULT_ACCEPTED, 0, 0,
                    message.get_srcSystem(), message.get_srcComponent(),
                )  # fmt: skip
                self.counts["ack"] += 1
            else:
                self.counts["other"] += 1

    def _setup_signing(self, message: Any) -> None:
        """A new key, as ArduPilot takes it (module docstring): all zero with a zero timestamp
        turns signing off; never while armed (the issue's rule, beyond ArduPilot's)."""
        if message.target_system not in {0, self.mav.srcSystem}:
            return
        if self.armed:
            self.counts["setup_refused_armed"] += 1
            return
        key = bytes(message.secret_key)
        self._use_key(key if any(key) or message.initial_timestamp else None)
        self.mav.signing.timestamp = max(self.mav.signing.timestamp, message.initial_timestamp)
        self.counts["setup_signing"] += 1

    def run(self, stop: threading.Event) -> None:
        """Telemetry every ``1 / rate_hz`` seconds, answers as frames come, until ``stop``."""
        period = 1.0 / self.rate_hz
        due = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            if now >= due:
                self.telemetry()
                due = max(due + period, now)
            self.poll(min(max(due - now, 0.0), 0.1))

    def poll(self, timeout: float) -> None:
        """Handle what arrives within ``timeout`` seconds (one read at most)."""
        source = self._sock.fileno() if self._sock is not None else self._master
        assert source is not None
        ready, _, _ = select.select([source], [], [], timeout)
        if ready:
            self.handle(os.read(source, 65_535))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
        if self._master is not None:
            os.close(self._master)
            os.close(self._slave)
