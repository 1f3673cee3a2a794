"""The router in a real setup: MAVProxy (from PyPI) as the ground station, signing by
passphrase; a pymavlink vehicle on a serial pseudo-terminal; a tool that cannot sign on a
trusted UDP endpoint; an attacker on the untrusted link.

MAVProxy takes its key from ``$HOME/.mavproxy/signing.keys`` (``ENDPOINT PASSPHRASE``),
as its users set it up, and forwards what an operator sends to its ``--out`` port, signed
(``mavfwd_signing``).  Every wait polls an observable event under a deadline.
"""

from __future__ import annotations

import os
import select
import socket
import subprocess
import sys
import threading
import tty
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

os.environ["MAVLINK20"] = "1"  # pymavlink's mavutil speaks MAVLink 1 unless told otherwise
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.audit import AuditLog
from antireplay.core.clock import SystemClock
from antireplay.mavlink import MavlinkRouter, Refusal, Role, mav_time, passphrase_key
from antireplay.state.sqlite import SqliteStore
from antireplay.wiring import RouterOptions, build_mavlink_router
from tests.harness import free_port, until

PASSPHRASE = "correct-horse-battery-staple"
KEY = passphrase_key(PASSPHRASE)
ARM = 400  # MAV_CMD_COMPONENT_ARM_DISARM
TOOL_SYSTEM = 200


class PtyVehicle:
    """A pymavlink vehicle (system 1) on the master side of a pseudo-terminal: signs what it
    sends (wall-anchored), verifies what it receives with the same key, keeps both; with
    ``key=None`` it neither signs nor verifies."""

    def __init__(self, key: bytes | None = KEY) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # a UART: no echo, no line editing, before anyone writes
        self.device = os.ttyname(self.slave)
        self.mav = dialect.MAVLink(self, srcSystem=1, srcComponent=1)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 3
        self.received: list[Any] = []  # every message that verified
        self.rejected = 0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=self._read), threading.Thread(target=self._beat)]
        for thread in self._threads:
            thread.start()

    def write(self, data: bytes) -> None:
        os.write(self.master, data)

    def send(self, build: Callable[[], None]) -> None:
        with self._lock:
            self.mav.signing.timestamp = max(self.mav.signing.timestamp, mav_time(SystemClock()))
            build()

    def commands(self, command: int | None = None) -> list[Any]:
        return [
            m for m in list(self.received)
            if m.get_type() == "COMMAND_LONG" and command in (None, m.command)
        ]  # fmt: skip

    def _beat(self) -> None:
        while not self._stop.wait(0.05):  # telemetry at 20 Hz: HEARTBEAT and ATTITUDE
            self.send(lambda: self.mav.heartbeat_send(2, 3, 0, 0, 4))
            self.send(lambda: self.mav.attitude_send(1, 0.1, 0.2, 0.3, 0, 0, 0))

    def _read(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.1)
            if not ready:
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:
                return
            for byte in data:
                try:
                    msg = self.mav.parse_char(bytes([byte]))
                except dialect.MAVError:
                    self.rejected += 1
                    continue
                if msg is None:
                    continue
                if msg.get_type() == "BAD_DATA":
                    self.rejected += 1
                else:
                    self.received.append(msg)

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join()
        os.close(self.master)
        os.close(self.slave)


def mavproxy(
    home: Path, master: str, out: str, passphrase: str | None = PASSPHRASE
) -> subprocess.Popen[bytes]:
    """MAVProxy, headless, signing its master link with the passphrase in signing.keys
    (``passphrase=None``: no key, no signing module, system 254)."""
    script = Path(sys.executable).parent / "mavproxy.py"
    if not script.exists():
        pytest.fail(f"MAVProxy is not installed ({script}): pip install -e '.[dev]'")
    if passphrase is not None:
        (home / ".mavproxy").mkdir(parents=True, exist_ok=True)
        (home / ".mavproxy" / "signing.keys").write_text(f"{master} {passphrase}\n")
    modules, system = ("signing", "255") if passphrase is not None else ("link", "254")
    args = [
        "--master", master, "--out", out, "--daemon", "--non-interactive", "--no-state",
        "--default-modules", modules, "--source-system", system, "--source-component", "190",
    ]  # fmt: skip
    return subprocess.Popen(
        [sys.executable, str(script), *args],
        env=dict(os.environ, HOME=str(home)),
        cwd=home,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


class Setup:
    """Vehicle on a pty, the router (a SQLite store), MAVProxy, an operator behind it,
    an unsigning tool on the trusted endpoint, an attacker's socket on the ground port."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.vehicle = PtyVehicle()
        self.ground_port, self.trusted_port = free_port(), free_port()
        self.router = self.start_router()
        self.operator_port = free_port()
        self.operator = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{self.operator_port}", source_system=250, source_component=1
        )
        self.proxy = mavproxy(
            tmp, f"udpout:127.0.0.1:{self.ground_port}", f"udpout:127.0.0.1:{self.operator_port}"
        )
        self.tool = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{self.trusted_port}", source_system=TOOL_SYSTEM, source_component=1
        )
        self.attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def start_router(self) -> MavlinkRouter:
        """A router on the SQLite store in ``tmp`` (a restart keeps it); refusals from now."""
        self.refused: list[Refusal] = []
        self.store = SqliteStore(self.tmp / "mav.db")
        self.audit = AuditLog(self.tmp / "audit.db")
        router = build_mavlink_router(
            [
                (Role.VEHICLE, f"{self.vehicle.device},57600", KEY),
                (Role.GROUND, f"udpin:127.0.0.1:{self.ground_port}", KEY),
                (Role.TRUSTED, f"udpin:127.0.0.1:{self.trusted_port}", None),
            ],
            self.store,
            self.audit,
            RouterOptions(system_id=1),
        )
        reported = router.on_reject
        assert reported is not None

        def keep(refusal: Refusal) -> None:
            self.refused.append(refusal)
            reported(refusal)  # the log line and the audit record, as in production

        router.on_reject = keep
        router.start()
        return router

    def stop_router(self) -> None:
        self.router.stop()
        self.audit.close()
        self.store.close()

    def inject(self, raw: bytes) -> None:
        self.attacker.sendto(raw, ("127.0.0.1", self.ground_port))

    def heard(self, conn: Any, system: int) -> Callable[[], bool]:
        """Whether ``conn`` has received a HEARTBEAT from ``system`` (drains what came)."""

        def check() -> bool:
            while (msg := conn.recv_match(type="HEARTBEAT", blocking=False)) is not None:
                if msg.get_srcSystem() == system:
                    return True
            return False

        return check

    def refusals_of(self, frames: list[bytes]) -> list[Refusal]:
        """The refusals of exactly these frames (other senders' drops are not counted)."""
        wanted = set(frames)
        return [refusal for refusal in list(self.refused) if refusal.raw in wanted]

    def close(self) -> None:
        self.proxy.terminate()
        self.proxy.wait(timeout=30)
        self.stop_router()
        for conn in (self.operator, self.tool):
            conn.close()
        self.attacker.close()
        self.vehicle.close()


@pytest.fixture
def setup(tmp_path: Path) -> Iterator[Setup]:
    made = Setup(tmp_path)
    try:
        yield made
    finally:
        made.close()


def test_mavproxy_ground_station_pty_vehicle_and_an_unsigning_tool(setup: Setup) -> None:
    vehicle, router = setup.vehicle, setup.router
    # Telemetry reaches every ground station once it has authenticated.
    until("vehicle telemetry at the operator behind MAVProxy", setup.heard(setup.operator, 1))
    setup.tool.mav.heartbeat_send(18, 8, 0, 0, 0)  # unsigned; the router signs it
    until("vehicle telemetry at the trusted tool", setup.heard(setup.tool, 1))

    # ARM from the operator, signed by MAVProxy with the passphrase's key, arrives once.
    setup.operator.mav.command_long_send(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0)
    until("ARM at the vehicle", lambda: vehicle.commands(ARM))
    arm = vehicle.commands(ARM)[0]
    assert arm.get_signed() and arm.get_srcSystem() == 255
    captured = bytes(arm.get_msgbuf())

    # Its replay from the untrusted link is dropped, and counted with its reason.
    setup.inject(captured)
    until("the replay refused", lambda: router.stats.dropped["inbound:COUNTER_REPLAYED"])

    # The tool's unsigned command reaches the vehicle signed, and pymavlink verifies it.
    setup.tool.mav.command_long_send(1, 1, 183, 0, 42, 0, 0, 0, 0, 0, 0)  # DO_SET_SERVO
    until("the tool's command at the vehicle", lambda: vehicle.commands(183))
    (servo,) = vehicle.commands(183)
    assert servo.get_signed() and servo.get_link_id() == 251
    assert servo.get_srcSystem() == TOOL_SYSTEM and servo.param1 == 42
    assert len(vehicle.commands(ARM)) == 1  # ARM arrived once

    # Frames injected on the untrusted link learn no route (forged, and unsigned).
    forger = dialect.MAVLink(_Keep(), srcSystem=77, srcComponent=1)
    forger.signing.secret_key, forger.signing.sign_outgoing = bytes(32), True
    forger.signing.timestamp = mav_time(SystemClock())
    forger.heartbeat_send(6, 8, 0, 0, 0)
    plain = dialect.MAVLink(_Keep(), srcSystem=78, srcComponent=1)
    plain.heartbeat_send(6, 8, 0, 0, 0)
    injected = [forger.file.frames[-1], plain.file.frames[-1]]
    for raw in injected:
        setup.inject(raw)
    until("both injected frames refused", lambda: len(setup.refusals_of(injected)) == 2)
    refused = [r.code for r in setup.refusals_of(injected)]
    assert refused == ["SIGNATURE_INVALID", "SIGNATURE_REQUIRED"]
    systems = {system for system, _ in router.routes()}
    assert {1, 255, TOOL_SYSTEM} <= systems and not {77, 78} & systems
    assert not any(m.get_srcSystem() in {77, 78} for m in vehicle.received)

    # Restart the router; replay every capture: all dropped.  The honest tool goes on.
    captures = [bytes(m.get_msgbuf()) for m in list(vehicle.received)]
    assert len(captures) >= 3
    setup.stop_router()
    setup.router = router = setup.start_router()
    for raw in captures:
        setup.inject(raw)
    until("every capture refused", lambda: len(setup.refusals_of(captures)) == len(captures))
    codes = {refusal.code for refusal in setup.refusals_of(captures)}
    assert codes <= {"MESSAGE_STALE", "COUNTER_REPLAYED", "WRONG_DIRECTION"}, codes
    seen = len(vehicle.received)
    setup.tool.mav.command_long_send(1, 1, 183, 0, 43, 0, 0, 0, 0, 0, 0)
    until("the tool's command after the restart", lambda: len(vehicle.commands(183)) == 2)
    assert vehicle.commands(183)[1].param1 == 43
    assert not {bytes(m.get_msgbuf()) for m in vehicle.received[len(captures) :]} & set(captures)
    assert vehicle.rejected == 0  # the vehicle's own check never had to refuse anything
    assert len(vehicle.received) > seen


class _Keep:
    """pymavlink's output file, kept in a list."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))
