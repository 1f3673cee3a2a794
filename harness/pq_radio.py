"""Post-quantum MAVLink commands, and signed MAVLink beside them, over a lossy, slow radio:
the processes of one run and what they count (the PQ radio benchmark and the CLI's radio
test both run it).

:func:`run_pq`: a pymavlink ground station (heartbeat at 1 Hz; each COMMAND_LONG tried up
to ``tries`` times ``retry_s`` apart until its COMMAND_ACK comes, as QGroundControl and
MAVProxy do) -> ``antireplay mavlink-pq ground`` -> the radio (:class:`harness.radio.Radio`:
independent loss per datagram, optionally a serial line with a SiK-sized queue) ->
``antireplay mavlink-pq vehicle`` -> a pymavlink vehicle (heartbeat at 1 Hz, a COMMAND_ACK
for every COMMAND_LONG).  The ends get ``--air-bps`` when the link is limited and
:attr:`Plan.air_bps` says the CLI has the option.  :func:`run_signed`: the deployed path
of the MAVLink guide: the same ground station signing by passphrase -> the radio ->
``antireplay mavlink-router`` (ground link verified, vehicle key the same) -> the vehicle.

A :class:`Row` counts commands delivered (an ACK within the tries), the time to each ACK,
air bytes (both directions, lost datagrams included) from the first command to the last,
and the time to the PQ session.  The vehicle counts each execution by command and by the
ground station's MAVLink sequence number, which tells one transmission from another:
``replays`` (a transmission executed twice), ``re_executed`` (a retry after a lost ACK ran
the command again), ``unacked_executed`` (executed while the ground station gave up).
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

os.environ["MAVLINK20"] = "1"  # pymavlink's mavutil speaks MAVLink 1 unless told otherwise
from pymavlink import mavutil

from antireplay.core.clock import ManualClock
from antireplay.mavlink import passphrase_key
from antireplay.state.sqlite import SqliteStore
from harness import free_udp_port
from harness.radio import Radio

CLI = [sys.executable, "-m", "antireplay"]
PASSPHRASE = "bench-radio-passphrase"
KEY = passphrase_key(PASSPHRASE)
SERVO = mavutil.mavlink.MAV_CMD_DO_SET_SERVO
PWM_BASE = 1000  # command i sets PWM_BASE + i: distinct commands, and the index on arrival
VEHICLE, GCS = (1, 1), (255, 190)
STARTUP_S = 30.0


@dataclass
class Row:
    """One path's run at one loss level on one link."""

    commands: int
    delivered: int = 0
    latencies: list[float] = field(default_factory=list)
    air_bytes: int = 0
    session_s: float | None = None
    replays: int = 0
    re_executed: int = 0
    unacked_executed: int = 0
    note: str = ""

    def p90(self) -> str:
        if not self.latencies:
            return "—"
        ranked = sorted(self.latencies)
        return f"{ranked[math.ceil(0.9 * len(ranked)) - 1]:.3f} s"

    def per_command(self) -> str:
        return f"{self.air_bytes / self.delivered:,.0f}" if self.delivered else "—"


class _Process:
    """A CLI subprocess whose stderr lines are kept, each with when it was read."""

    def __init__(self, args: list[str], cwd: Path, env: dict[str, str] | None = None) -> None:
        self.lines: list[tuple[float, str]] = []
        self.proc = subprocess.Popen(
            [*CLI, *args], cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True, env=env,
        )  # fmt: skip
        self._readers = [
            threading.Thread(target=self._read, args=(stream,), daemon=True)
            for stream in (self.proc.stdout, self.proc.stderr)
        ]
        for reader in self._readers:
            reader.start()

    def _read(self, stream: Any) -> None:
        for line in stream:
            self.lines.append((time.monotonic(), line.rstrip("\n")))

    def said(self, text: str) -> float | None:
        """When a line containing ``text`` was read (None: not yet)."""
        return next((at for at, line in list(self.lines) if text in line), None)

    def wait_for(self, text: str, timeout: float = STARTUP_S) -> None:
        deadline = time.monotonic() + timeout
        while self.said(text) is None:
            if self.proc.poll() is not None or time.monotonic() > deadline:
                said = "\n".join(line for _, line in self.lines)
                raise SystemExit(f"{self.proc.args!r} never said {text!r}:\n{said}")
            time.sleep(0.01)

    def stop(self) -> str:
        """SIGTERM, wait; the last line it printed (its counts)."""
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for reader in self._readers:
            reader.join(timeout=5)
        return self.lines[-1][1] if self.lines else ""


class _Peer:
    """A pymavlink connection with a reader thread and a 1 Hz heartbeat."""

    def __init__(self, conn: Any, heartbeat: tuple[int, int]) -> None:
        self.conn = conn
        self.lock = threading.Lock()
        self._heartbeat = heartbeat
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._beat, daemon=True),
            threading.Thread(target=self._read, daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def _beat(self) -> None:
        while True:
            with self.lock:
                self.conn.mav.heartbeat_send(*self._heartbeat, 0, 0, 0)
            if self._stop.wait(1.0):
                return

    def _read(self) -> None:
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.1)
            if msg is not None:
                self.handle(msg)

    def handle(self, msg: Any) -> None:
        raise NotImplementedError

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join()
        self.conn.close()


class Vehicle(_Peer):
    """Answers every COMMAND_LONG with a COMMAND_ACK carrying its index; counts executions."""

    def __init__(self, conn: Any) -> None:
        self.executed: dict[int, list[int]] = {}  # command index -> the GCS seq of each run
        super().__init__(conn, (mavutil.mavlink.MAV_TYPE_QUADROTOR, 3))

    def handle(self, msg: Any) -> None:
        if msg.get_type() != "COMMAND_LONG" or msg.command != SERVO:
            return
        index = int(msg.param2) - PWM_BASE
        self.executed.setdefault(index, []).append(msg.get_seq())
        with self.lock:
            self.conn.mav.command_ack_send(
                SERVO, mavutil.mavlink.MAV_RESULT_ACCEPTED, 0, index, *GCS
            )


class GroundStation(_Peer):
    """Sends the commands, one at a time, each retried until its ACK or out of tries."""

    def __init__(self, conn: Any) -> None:
        self.acked: dict[int, float] = {}
        self.heard = threading.Event()
        self.arrived = threading.Condition()
        super().__init__(conn, (mavutil.mavlink.MAV_TYPE_GCS, 8))

    def handle(self, msg: Any) -> None:
        if msg.get_type() == "HEARTBEAT" and msg.get_srcSystem() == VEHICLE[0]:
            self.heard.set()
        elif msg.get_type() == "COMMAND_ACK" and msg.command == SERVO:
            with self.arrived:
                self.acked.setdefault(msg.result_param2, time.monotonic())
                self.arrived.notify_all()

    def command(self, index: int, tries: int, retry_s: float) -> float | None:
        """Seconds from the first try to the ACK (None: every try timed out)."""
        start = time.monotonic()
        for attempt in range(tries):
            with self.lock:
                self.conn.mav.command_long_send(
                    *VEHICLE, SERVO, 0, 9, PWM_BASE + index, 0, 0, 0, 0, 0
                )
            deadline = start + (attempt + 1) * retry_s
            with self.arrived:
                while index not in self.acked and time.monotonic() < deadline:
                    self.arrived.wait(deadline - time.monotonic())
                if index in self.acked:
                    return self.acked[index] - start
        return None


@dataclass(frozen=True)
class Plan:
    commands: int
    tries: int
    retry_s: float
    session_timeout_s: float
    queue_bytes: int
    keys: Path
    air_bps: bool


def _run_commands(row: Row, gcs: GroundStation, vehicle: Vehicle, radio: Radio, plan: Plan) -> None:
    before = radio.on_air_bytes()
    for index in range(plan.commands):
        latency = gcs.command(index, plan.tries, plan.retry_s)
        if latency is not None:
            row.delivered += 1
            row.latencies.append(latency)
    row.air_bytes = radio.on_air_bytes() - before
    executed = dict(vehicle.executed)
    row.replays = sum(n - 1 for seqs in executed.values() for n in Counter(seqs).values() if n > 1)
    row.re_executed = sum(1 for seqs in executed.values() if len(set(seqs)) > 1)
    row.unacked_executed = sum(1 for index in executed if index not in gcs.acked)


@contextmanager
def _closing(peer: _Peer) -> Iterator[_Peer]:
    try:
        yield peer
    finally:
        peer.close()


def run_pq(loss: float, bps: int | None, seed: int, plan: Plan) -> Row:
    """One PQ run: fresh ends, radio, ground station and vehicle."""
    row = Row(plan.commands)
    fc, air, local = free_udp_port(), free_udp_port(), free_udp_port()
    pace = ["--air-bps", str(bps)] if bps is not None and plan.air_bps else []
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:
        work = Path(tmp)
        vehicle = Vehicle(
            mavutil.mavlink_connection(f"udpin:127.0.0.1:{fc}", source_system=VEHICLE[0])
        )
        stack.enter_context(_closing(vehicle))
        vehicle_end = _Process(
            [
                "mavlink-pq", "vehicle", "--fc", f"udpout:127.0.0.1:{fc}",
                "--air", f"udpin:127.0.0.1:{air}", "--kem-key", str(plan.keys / "vehicle.key.pem"),
                "--peer", f"gcs={plan.keys / 'gcs.pub.pem'}", "--audit", str(work / "v.db"), *pace,
            ],
            work,
        )  # fmt: skip
        stack.callback(vehicle_end.stop)
        vehicle_end.wait_for("mavlink-pq vehicle")
        radio = Radio(
            ("127.0.0.1", air), loss=loss, bps=bps, queue_bytes=plan.queue_bytes, seed=seed
        )
        stack.enter_context(radio)
        gcs = GroundStation(
            mavutil.mavlink_connection(
                f"udpout:127.0.0.1:{local}", source_system=GCS[0], source_component=GCS[1]
            )
        )
        stack.enter_context(_closing(gcs))
        ground_end = _Process(
            [
                "mavlink-pq", "ground", "--local", f"udpin:127.0.0.1:{local}",
                "--air", f"udpout:127.0.0.1:{radio.port}",
                "--signing-key", str(plan.keys / "gcs.key.pem"),
                "--vehicle-key", str(plan.keys / "vehicle.pub.pem"),
                "--audit", str(work / "g.db"), *pace,
            ],
            work,
        )  # fmt: skip
        stack.callback(ground_end.stop)
        ground_end.wait_for("mavlink-pq ground")
        deadline = time.monotonic() + plan.session_timeout_s
        while (up := ground_end.said("session established")) is None:
            if time.monotonic() > deadline:
                row.note = f"no session in {plan.session_timeout_s:.0f} s"
                return row
            time.sleep(0.01)
        first = radio.counts()["uplink"].first_at
        row.session_s = up - first if first is not None else None
        _run_commands(row, gcs, vehicle, radio, plan)
    return row


def run_signed(loss: float, bps: int | None, seed: int, plan: Plan) -> Row:
    """One signed-MAVLink run: the router verifying the ground link, the same radio."""
    row = Row(plan.commands)
    vehicle_port, ground_port = free_udp_port(), free_udp_port()
    env = dict(os.environ, MAV_PASSPHRASE=PASSPHRASE)
    with tempfile.TemporaryDirectory() as tmp, ExitStack() as stack:
        work = Path(tmp)
        # A deployment started 10 min ago: a new state fences the router's first start.
        SqliteStore(work / "mav.db", clock=ManualClock(wall=time.time() - 600)).close()
        router = _Process(
            [
                "mavlink-router", "--vehicle", f"udpin:127.0.0.1:{vehicle_port}",
                "--ground", f"udpin:127.0.0.1:{ground_port}", "--passphrase-env",
                "MAV_PASSPHRASE", "--system-id", "1", "--store", f"sqlite:{work / 'mav.db'}",
                "--audit", str(work / "audit.db"),
            ],
            work,
            env,
        )  # fmt: skip
        stack.callback(router.stop)
        router.wait_for("mavlink-router")
        fc = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{vehicle_port}", source_system=VEHICLE[0]
        )
        fc.setup_signing(KEY, sign_outgoing=True, link_id=2)
        vehicle = Vehicle(fc)
        stack.enter_context(_closing(vehicle))
        radio = Radio(
            ("127.0.0.1", ground_port), loss=loss, bps=bps, queue_bytes=plan.queue_bytes,
            seed=seed,
        )  # fmt: skip
        stack.enter_context(radio)
        conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{radio.port}", source_system=GCS[0], source_component=GCS[1]
        )
        conn.setup_signing(KEY, sign_outgoing=True, link_id=1)
        gcs = GroundStation(conn)
        stack.enter_context(_closing(gcs))
        started = time.monotonic()
        if not gcs.heard.wait(plan.session_timeout_s):
            row.note = f"no telemetry in {plan.session_timeout_s:.0f} s"
            return row
        row.session_s = time.monotonic() - started
        _run_commands(row, gcs, vehicle, radio, plan)
    return row


def make_keys(where: Path) -> None:
    for alg, out in (("ml-dsa-87", "gcs"), ("ml-kem-1024", "vehicle")):
        subprocess.run(
            [*CLI, "keygen", "--alg", alg, "--out", str(where / out)],
            check=True, stdout=subprocess.DEVNULL,
        )  # fmt: skip


def supports_air_bps() -> bool:
    """Whether both ends of this checkout take ``--air-bps`` (the same benchmark runs on
    code from before the option)."""
    return all(
        "--air-bps" in subprocess.run(
            [*CLI, "mavlink-pq", end, "--help"], capture_output=True, text=True, check=True
        ).stdout
        for end in ("ground", "vehicle")
    )  # fmt: skip
