"""MAVProxy test beds: a pymavlink vehicle on a serial pseudo-terminal, MAVProxy headless
(from PyPI), and the two rigs built from them.

:class:`RouterRig`: the router (SQLite store) between the vehicle, MAVProxy signing by
passphrase with an operator behind it, an unsigning tool on a trusted endpoint and an
attacker's socket on the ground port.  :class:`PqRig`: ground station -> ground end ->
MAVProxy (no key, no dialect of ours) -> vehicle end -> vehicle, an attacker on the air.
"""

from __future__ import annotations

import os
import select
import socket
import subprocess
import sys
import threading
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from cryptography.hazmat.primitives.asymmetric import mldsa, mlkem

os.environ["MAVLINK20"] = "1"  # pymavlink's mavutil speaks MAVLink 1 unless told otherwise
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.audit import AuditLog
from antireplay.core.clock import SystemClock
from antireplay.mavlink import FrameRefusal, MavlinkRouter, Role, mav_time, passphrase_key
from antireplay.mavlink.endpoints import open_transport, parse_endpoint
from antireplay.mavlink.pq import GroundEnd, VehicleEnd
from antireplay.mavlink.pq.link import PqLink
from antireplay.pq.session import Initiator, Responder
from antireplay.state.sqlite import SqliteStore
from antireplay.wiring import RouterOptions, build_mavlink_router
from harness import free_port
from harness.stores import aged_state

PASSPHRASE = "correct-horse-battery-staple"


KEY = passphrase_key(PASSPHRASE)


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


class RouterRig:
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
        self.refused: list[FrameRefusal] = []
        self.store = SqliteStore(aged_state(self.tmp / "mav.db"))  # started earlier, or kept
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

        def keep(refusal: FrameRefusal) -> None:
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

    def refusals_of(self, frames: list[bytes]) -> list[FrameRefusal]:
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


GCS_KEY = mldsa.MLDSA87PrivateKey.generate()


ROBOT_KEM = mlkem.MLKEM1024PrivateKey.generate()


class PqRig:
    """GCS -> ground end -> MAVProxy -> vehicle end -> pty vehicle, an attacker on the air."""

    def __init__(self, tmp: Path) -> None:
        self.vehicle = PtyVehicle(key=None)  # the vehicle end is its only link
        self.ground_port, self.proxy_port, self.air_port = free_port(), free_port(), free_port()
        self.captured: list[bytes] = []  # every frame the ground end put on the air
        self.vehicle_link = self.start_vehicle_end()
        self.ground_link = self.start_ground_end()
        master, out = f"udpout:127.0.0.1:{self.air_port}", f"udpin:127.0.0.1:{self.proxy_port}"
        self.proxy = mavproxy(tmp, master, out, passphrase=None)  # no key, no dialect of ours
        self.gcs = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{self.ground_port}", source_system=255, source_component=190
        )
        self.attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._stop = threading.Event()
        self._beat = threading.Thread(target=self._gcs_beat)
        self._beat.start()

    def start_vehicle_end(self) -> PqLink:
        self.responder = Responder(ROBOT_KEM, {"gcs": GCS_KEY.public_key()}, max_sessions=4)
        link = PqLink(
            VehicleEnd(self.responder),
            open_transport(parse_endpoint(f"{self.vehicle.device},57600")),
            open_transport(parse_endpoint(f"udpin:127.0.0.1:{self.air_port}")),
        )
        link.start()
        return link

    def start_ground_end(self) -> PqLink:
        end = GroundEnd(Initiator("gcs", GCS_KEY), ROBOT_KEM.public_key())
        link = PqLink(
            end,
            open_transport(parse_endpoint(f"udpin:127.0.0.1:{self.ground_port}")),
            open_transport(parse_endpoint(f"udpout:127.0.0.1:{self.proxy_port}")),
            tap=self.captured.append,
        )
        link.start()
        return link

    def _gcs_beat(self) -> None:
        while not self._stop.wait(0.1):  # a ground station's heartbeat at 10 Hz
            self.gcs.mav.heartbeat_send(6, 8, 0, 0, 0)

    def heard_vehicle(self) -> bool:
        while (msg := self.gcs.recv_match(type="HEARTBEAT", blocking=False)) is not None:
            if msg.get_srcSystem() == 1:
                return True
        return False

    def inject(self, frames: list[bytes]) -> None:
        for raw in frames:
            self.attacker.sendto(raw, ("127.0.0.1", self.air_port))

    def close(self) -> None:
        self._stop.set()
        self._beat.join()
        self.proxy.terminate()
        self.proxy.wait(timeout=30)
        self.ground_link.stop()
        self.vehicle_link.stop()
        self.gcs.close()
        self.attacker.close()
        self.vehicle.close()
