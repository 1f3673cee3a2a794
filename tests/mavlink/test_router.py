"""MAVLink router: a ground link and a vehicle link, real pymavlink at both ends over UDP."""

from __future__ import annotations

import os
import queue
import random
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

os.environ["MAVLINK20"] = "1"  # pymavlink's mavutil speaks MAVLink 1 unless told otherwise
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay import ManualClock
from antireplay.cli import main
from antireplay.cli.mavlink import _signing_key
from antireplay.core.clock import SystemClock
from antireplay.core.errors import StateUnavailableError
from antireplay.mavlink import (
    TS_LIMIT,
    FrameRefusal,
    MavlinkGuard,
    MavlinkRouter,
    Role,
    RouterLink,
    TimestampSource,
    codec,
    mav_time,
    open_transport,
    parse_endpoint,
    parse_frame,
)
from antireplay.mavlink import guard as guard_module
from antireplay.mavlink.binding import BIND_IDLE_S
from antireplay.mavlink.codec import UNITS_PER_S, Frame
from antireplay.state.memory import MemoryStore
from antireplay.state.sqlite import SqliteStore
from harness import ROOT, free_port, free_udp_port, until
from harness.mavlink_frames import KEY, FakeTransport, Sink, unsigned_heartbeat
from harness.stores import aged_state


class Rig:
    """GCS (pymavlink, signing) -> router -> vehicle (pymavlink, observing everything)."""

    def __init__(
        self,
        system_id: int = 1,
        *,
        bind_system_id: bool = True,
        allow_unsigned: frozenset[int] = frozenset(),
    ) -> None:
        vport = free_udp_port()
        self.vehicle = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{vport}", source_system=system_id, source_component=1
        )
        self.rejections: queue.Queue[tuple[str, str]] = queue.Queue()
        self.ground = RouterLink(
            open_transport(parse_endpoint("udpin:127.0.0.1:0")), Role.GROUND, KEY
        )
        vehicle = open_transport(parse_endpoint(f"udpout:127.0.0.1:{vport}"))
        inbound = MavlinkGuard(
            KEY, system_id=system_id if bind_system_id else None, allow_unsigned=allow_unsigned
        )
        self.router = MavlinkRouter(
            [self.ground, RouterLink(vehicle, Role.VEHICLE, KEY)],
            {KEY: inbound},
            MavlinkGuard(KEY),
            on_reject=self._rejected,
        )
        self.inbound = inbound
        self.router.start()
        self.address = self.ground.transport.address
        host, port = self.address
        self.gcs = mavutil.mavlink_connection(
            f"udpout:{host}:{port}", source_system=255, source_component=190
        )
        self.gcs.setup_signing(KEY, sign_outgoing=True, link_id=1)
        self.raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def send_command(self, param1: float, target: int = 1) -> bytes:
        msg = self.gcs.mav.command_long_encode(target, 1, 400, 0, param1, 0, 0, 0, 0, 0, 0)
        self.gcs.mav.send(msg)
        return bytes(msg.get_msgbuf())

    def _rejected(self, refusal: FrameRefusal) -> None:
        self.rejections.put((refusal.direction, refusal.code))

    @property
    def peer(self) -> tuple[str, int] | None:
        """The ground peer that authenticated last (where telemetry goes)."""
        peers = [peer for peer in self.ground.peers if isinstance(peer, tuple)]
        return peers[-1] if peers else None

    def inject(self, raw: bytes) -> None:
        self.raw.sendto(raw, self.address)

    def commands_until(self, sentinel: float) -> list[float]:
        """Every COMMAND_LONG param1 the vehicle received, up to and including the sentinel."""
        seen: list[float] = []
        while True:
            msg = self.vehicle.recv_match(type="COMMAND_LONG", blocking=True, timeout=10)
            assert msg is not None, f"sentinel {sentinel} never arrived; got {seen}"
            seen.append(float(msg.param1))
            if msg.param1 == sentinel:
                return seen

    def rejected(self) -> tuple[str, str]:
        """The next rejection the router reported (direction, code); the router calls back."""
        try:
            return self.rejections.get(timeout=10)
        except queue.Empty:
            pytest.fail("the router reported no rejection")

    def close(self) -> None:
        self.router.stop()
        self.gcs.close()
        self.vehicle.close()
        self.raw.close()


@pytest.fixture
def rig() -> Iterator[Rig]:
    made = Rig()
    yield made
    made.close()


@pytest.mark.parametrize("role", list(Role), ids=str)
def test_roles_print_as_their_value(role: Role) -> None:
    """Roles are named in endpoint specs and log lines by their value."""
    assert str(role) == f"{role}" == role.value


def test_command_arrives_once_and_exact_replay_is_dropped(rig: Rig) -> None:
    captured = rig.send_command(1.0)
    assert rig.commands_until(1.0) == [1.0]
    rig.inject(captured)
    rig.send_command(2.0)
    assert rig.commands_until(2.0) == [2.0]
    assert rig.router.stats.dropped["inbound:COUNTER_REPLAYED"] == 1


def test_jamming_through_the_router(rig: Rig) -> None:
    frame = bytearray(rig.send_command(1.0))
    rig.commands_until(1.0)
    frame[-12:-6] = (TS_LIMIT - 1).to_bytes(6, "little")
    rig.inject(bytes(frame))
    rig.send_command(2.0)
    assert rig.commands_until(2.0) == [2.0]
    assert rig.router.stats.dropped["inbound:MESSAGE_FROM_FUTURE"] == 1  # before any crypto


def test_thousand_forged_streams_through_the_router(rig: Rig) -> None:
    rig.send_command(1.0)
    rig.commands_until(1.0)
    before = len(rig.inbound)
    rng = random.Random(11)
    for i in range(1_000):
        forger = dialect.MAVLink(
            Sink(), srcSystem=rng.randint(1, 250), srcComponent=rng.randint(1, 250)
        )
        forger.signing.secret_key = os.urandom(32)
        forger.signing.sign_outgoing = True
        forger.signing.link_id = rng.randint(0, 255)
        forger.signing.timestamp = mav_time(ManualClock(time.time()))
        forger.command_long_send(1, 1, 400, 0, 9.0, 0, 0, 0, 0, 0, 0)
        rig.inject(forger.file.frames[-1])
        if i % 100 == 99:  # paced: a loaded box must not lose datagrams in the socket buffer

            def judged(n: int = i + 1) -> bool:
                return sum(rig.router.stats.dropped.values()) >= n

            until("forgeries judged", judged)
    rig.send_command(2.0)
    assert rig.commands_until(2.0) == [2.0]
    assert len(rig.inbound) == before


def test_malformed_datagrams_counted_and_dropped(rig: Rig) -> None:
    for bad in (b"\xfd\x05", b"hello", bytes(3), b"\xfd\x09\x00\x00\x01\xff\xbe\x4c\x00\x00"):
        rig.inject(bad)
    rig.send_command(3.0)
    assert rig.commands_until(3.0) == [3.0]
    assert rig.router.stats.dropped["inbound:INVALID_FRAME"] == 4


def test_a_datagram_is_whole_frames_or_dropped(rig: Rig) -> None:
    """An authentic frame with garbage before or after it, or cut short, in one datagram:
    the datagram is dropped whole and counted (no resynchronising on a datagram); two
    whole frames in one datagram both pass."""
    mav, sink = signed_sender(254, KEY, ManualClock(time.time()))

    def command(param1: float) -> bytes:
        mav.command_long_send(1, 1, 400, 0, param1, 0, 0, 0, 0, 0, 0)
        return sink.frames[-1]

    for datagram in (b"\x00" + command(1.0), command(2.0) + b"\xfd\x01", command(3.0)[:-1]):
        rig.inject(datagram)
    rig.inject(command(4.0) + command(5.0))
    rig.inject(command(6.0))
    assert rig.commands_until(6.0) == [4.0, 5.0, 6.0]
    assert rig.router.stats.dropped == {"inbound:INVALID_FRAME": 3}


def test_replay_towards_a_second_vehicle_is_dropped(rig: Rig) -> None:
    captured = rig.send_command(1.0, target=1)
    rig.commands_until(1.0)
    second = Rig(system_id=2)
    try:
        second.inject(captured)
        second.send_command(5.0, target=2)
        assert second.commands_until(5.0) == [5.0]
        assert second.router.stats.dropped["inbound:WRONG_TARGET"] == 1
    finally:
        second.close()


def test_round_trip_both_directions_with_signing_everywhere() -> None:
    rig = Rig()
    try:
        rig.vehicle.setup_signing(KEY, sign_outgoing=True, link_id=7)
        rig.send_command(1.0)
        assert rig.commands_until(1.0) == [1.0]
        rig.vehicle.mav.heartbeat_send(2, 3, 0, 0, 4)
        reply = rig.gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=10)
        assert reply is not None and reply.get_srcSystem() == 1
        assert rig.router.stats.forwarded["outbound"] >= 1
    finally:
        rig.close()


def any_id(_mav: object, _msgid: int) -> bool:
    """pymavlink's hook: the vehicle takes unsigned frames (the router's allow-list decides)."""
    return True


def forged_command() -> bytes:
    forger = dialect.MAVLink(Sink(), srcSystem=255, srcComponent=190)
    forger.signing.secret_key = bytes(32)  # not the link key
    forger.signing.sign_outgoing = True
    forger.signing.link_id = 1
    forger.signing.timestamp = mav_time(ManualClock(time.time()))
    forger.command_long_send(1, 1, 400, 0, 9.0, 0, 0, 0, 0, 0, 0)
    return bytes(forger.file.frames[-1])


@pytest.mark.parametrize("attack", ["garbage", "forged", "replayed", "unsigned-allow-listed"])
def test_unauthenticated_datagram_cannot_steal_telemetry(attack: str) -> None:
    """One datagram from an attacker's address must not move the ground peer."""
    rig = Rig(allow_unsigned=frozenset({0}))  # HEARTBEAT may come unsigned
    try:
        rig.vehicle.setup_signing(
            KEY, sign_outgoing=True, link_id=7, allow_unsigned_callback=any_id
        )
        captured = rig.send_command(1.0)
        assert rig.commands_until(1.0) == [1.0]
        gcs_address = ("127.0.0.1", rig.gcs.port.getsockname()[1])
        assert rig.peer == gcs_address
        if attack == "unsigned-allow-listed":
            rig.inject(unsigned_heartbeat(sysid=200))
            got = rig.vehicle.recv_match(type="HEARTBEAT", blocking=True, timeout=10)
            assert got is not None and got.get_srcSystem() == 200  # forwarded, by policy
        else:
            datagram = {"garbage": b"hello", "forged": forged_command(), "replayed": captured}
            rig.inject(datagram[attack])
            code = {"garbage": "INVALID_FRAME", "forged": "SIGNATURE_INVALID"}
            assert rig.rejected() == ("inbound", code.get(attack, "COUNTER_REPLAYED"))
        assert rig.peer == gcs_address
        rig.vehicle.mav.heartbeat_send(2, 3, 0, 0, 4)  # telemetry, signed by the vehicle
        reply = rig.gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=10)
        assert reply is not None and reply.get_srcSystem() == 1
        rig.raw.setblocking(False)
        with pytest.raises(BlockingIOError):
            rig.raw.recv(65_535)  # the attacker received nothing
    finally:
        rig.close()


def test_no_telemetry_before_a_ground_station_authenticated() -> None:
    rig = Rig(allow_unsigned=frozenset({0}))
    try:
        rig.vehicle.setup_signing(
            KEY, sign_outgoing=True, link_id=7, allow_unsigned_callback=any_id
        )
        rig.inject(unsigned_heartbeat(sysid=200))  # an unsigned frame teaches no peer
        assert rig.vehicle.recv_match(type="HEARTBEAT", blocking=True, timeout=10) is not None
        assert rig.peer is None
        rig.send_command(1.0)
        assert rig.commands_until(1.0) == [1.0]
        assert rig.peer == ("127.0.0.1", rig.gcs.port.getsockname()[1])
    finally:
        rig.close()


@pytest.mark.parametrize("bind_system_id", [True, False])
def test_reflected_vehicle_frame_is_dropped_with_a_typed_code(bind_system_id: bool) -> None:
    """A signed frame the vehicle sent, sent back to the listen port, never reaches it."""
    rig = Rig(bind_system_id=bind_system_id)
    try:
        rig.vehicle.setup_signing(KEY, sign_outgoing=True, link_id=7)
        rig.send_command(1.0)
        assert rig.commands_until(1.0) == [1.0]
        rig.vehicle.mav.command_long_send(255, 190, 400, 0, 7.0, 0, 0, 0, 0, 0, 0)
        reply = rig.gcs.recv_match(type="COMMAND_LONG", blocking=True, timeout=10)
        assert reply is not None and reply.get_srcSystem() == 1
        rig.inject(bytes(reply.get_msgbuf()))  # reflected to the ground side
        assert rig.rejected() == ("inbound", "WRONG_DIRECTION")
        rig.send_command(2.0)
        assert rig.commands_until(2.0) == [2.0]  # the reflected 7.0 never arrived
        assert rig.router.stats.forwarded["inbound"] == 2
    finally:
        rig.close()


def test_ground_frame_echoed_by_the_vehicle_side_is_dropped() -> None:
    """Radios and routers that echo: a ground frame coming back never reaches the ground."""
    rig = Rig()
    try:
        captured = rig.send_command(1.0)
        assert rig.commands_until(1.0) == [1.0]
        rig.vehicle.write(captured)  # the vehicle side sends the ground station's frame back
        assert rig.rejected() == ("outbound", "WRONG_DIRECTION")
        assert rig.router.stats.forwarded["outbound"] == 0
    finally:
        rig.close()


class _UdpWriter:
    """pymavlink's output file: each packed frame goes out as one datagram, and is kept."""

    def __init__(self, to: tuple[str, int]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.to = to
        self.sent: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.sent.append(bytes(data))
        self.sock.sendto(data, self.to)


def _paced(count: int, hz: float, send: Any) -> None:
    """Call ``send(i)`` ``count`` times at ``hz`` (a load generator's pacing, not a wait)."""
    start = time.perf_counter()
    for i in range(count):
        delay = start + i / hz - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        send(i)


def _dropped(metrics_port: int) -> dict[str, float]:
    with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=10) as reply:
        text = reply.read().decode()
    found = {}
    for line in text.splitlines():
        if line.startswith("antireplay_mavlink_dropped_total{"):
            labels, _, value = line.rpartition(" ")
            found[labels.split('code="')[1].split('"')[0]] = float(value)
    return found


def _until_dropped(metrics_port: int, count: int) -> None:
    """Poll the router's metrics until it has refused ``count`` frames (fail after 20 s)."""
    deadline = time.monotonic() + 20
    while sum(_dropped(metrics_port).values()) < count:
        if time.monotonic() > deadline:
            pytest.fail(f"the router judged fewer than {count} replays: {_dropped(metrics_port)}")
        time.sleep(0.02)


SENTINEL_MS = 4_000_000_000


def test_cli_proxy_kill_9_at_1000_hz_then_every_capture_dropped(tmp_path: Path) -> None:
    """A real proxy on its default SQLite store, signed ATTITUDE at 1,000 Hz from pymavlink,
    SIGKILL mid-stream, restart, replay every capture: all dropped; the sender goes on."""
    key_file = tmp_path / "key.hex"
    key_file.write_text(KEY.hex())
    vport, pport, mport = free_udp_port(), free_udp_port(), free_port()
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", vport))
    vehicle.settimeout(0.2)
    received: list[bytes] = []
    sentinel_seen, closing = threading.Event(), threading.Event()

    def vehicle_loop() -> None:
        while not closing.is_set():
            try:
                datagram = vehicle.recv(65_535)
            except TimeoutError:
                continue
            received.append(datagram)
            if int.from_bytes(datagram[10:14], "little") == SENTINEL_MS:
                sentinel_seen.set()

    args = [
        sys.executable, "-m", "antireplay", "mavlink-router", "--listen", f"udp:127.0.0.1:{pport}",
        "--forward", f"udp:127.0.0.1:{vport}", "--key-file", str(key_file), "--system-id", "1",
        "--store", f"sqlite:{aged_state(tmp_path / 'mav.db')}",  # started earlier
        "--audit", str(tmp_path / "audit.db"), "--metrics-port", str(mport),
    ]  # fmt: skip
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))

    def start() -> subprocess.Popen[bytes]:
        proc = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert proc.stdout is not None
        if b"mavlink-router" not in proc.stdout.readline():  # listening
            pytest.fail(f"the router did not start: {proc.communicate()[1].decode()}")
        return proc

    out = _UdpWriter(("127.0.0.1", pport))
    gcs = dialect.MAVLink(out, srcSystem=255, srcComponent=190)
    gcs.signing.secret_key, gcs.signing.sign_outgoing, gcs.signing.link_id = KEY, True, 1
    wall = SystemClock()

    def send(time_boot_ms: int) -> None:
        """Wall-anchored, as the spec asks (pymavlink alone only adds 1 per frame)."""
        gcs.signing.timestamp = max(gcs.signing.timestamp, mav_time(wall))
        gcs.attitude_send(time_boot_ms, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0)

    receiver = threading.Thread(target=vehicle_loop)
    receiver.start()
    proxy = start()
    try:

        def attitude(i: int) -> None:
            send(i + 1)
            if i == 1_500:
                proxy.send_signal(signal.SIGKILL)  # mid-stream

        _paced(2_000, 1_000, attitude)
        proxy.wait()
        forwarded_before = len(received)
        assert forwarded_before >= 1_000, forwarded_before  # the stream was flowing
        captures = list(out.sent)
        proxy = start()
        raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for batch in range(0, len(captures), 100):  # each batch judged before the next one
            size = min(100, len(captures) - batch)
            _paced(size, 1_000, lambda i, at=batch: raw.sendto(captures[at + i], out.to))
            _until_dropped(mport, batch + size)
        raw.close()
        _paced(50, 1_000, lambda i: send(10_000 + i))
        send(SENTINEL_MS)
        if not sentinel_seen.wait(10):
            pytest.fail("the honest sender's frames never passed the restarted router")
        after = received[forwarded_before:]
        assert not set(after) & set(captures)  # not one capture got through
        assert len(after) == 51  # every fresh frame did
        dropped = _dropped(mport)
        assert sum(dropped.values()) == len(captures), dropped
        assert set(dropped) <= {"MESSAGE_STALE", "COUNTER_REPLAYED"}, dropped
    finally:
        proxy.terminate()
        proxy.wait()
        closing.set()
        receiver.join()
        vehicle.close()
        out.sock.close()


def test_signing_key_file_forms(tmp_path: Path) -> None:
    raw = tmp_path / "raw.key"
    raw.write_bytes(b"\n" + bytes(range(1, 31)) + b" ")  # a raw key may start/end with whitespace
    assert _signing_key(raw) == b"\n" + bytes(range(1, 31)) + b" "
    hexed = tmp_path / "hex.key"
    hexed.write_text(KEY.hex() + "\n")
    assert _signing_key(hexed) == KEY


@pytest.mark.parametrize("content", [None, b"", b"zz" * 32, b"\xff" * 64, b"0" * 63])
def test_cli_proxy_refuses_a_bad_key_file_naming_it(tmp_path: Path, content: bytes | None) -> None:
    key = tmp_path / "link.key"
    if content is None:
        key.mkdir()  # a directory where the key should be
    else:
        key.write_bytes(content)
    result = CliRunner().invoke(main, [
        "mavlink-proxy", "--listen", "udp:127.0.0.1:9", "--forward", "udp:127.0.0.1:9",
        "--key-file", str(key), "--audit", str(tmp_path / "audit.db"),
    ])  # fmt: skip
    assert result.exit_code == 2
    said = " ".join(result.output.split())
    assert str(key) in said and "Traceback" not in said
    assert not (tmp_path / "audit.db").exists()


def test_an_audit_trail_that_is_down_does_not_stop_the_forwarding(rig: Rig) -> None:
    def audit_down(refusal: FrameRefusal) -> None:
        raise StateUnavailableError("audit trail: disk full")

    rig.router.on_reject = audit_down
    rig.inject(b"hello")
    rig.send_command(4.0)
    assert rig.commands_until(4.0) == [4.0]  # the receiving thread is alive
    assert rig.router.stats.unaudited == 1
    assert rig.router.stats.dropped["inbound:INVALID_FRAME"] == 1


def signed_sender(sysid: int, key: bytes, clock: ManualClock) -> tuple[Any, Sink]:
    sink = Sink()
    mav = dialect.MAVLink(sink, srcSystem=sysid, srcComponent=190)
    mav.signing.secret_key, mav.signing.sign_outgoing = key, True
    mav.signing.link_id, mav.signing.timestamp = 1, mav_time(clock)
    return mav, sink


def test_a_frame_the_router_signed_for_a_ground_link_cannot_be_reflected() -> None:
    """RouterLink B has its own key: the router signs what it forwards there afresh (link id
    251).  An attacker on B who sends such a copy back is refused (SOURCE_BOUND): it neither
    reaches the vehicle twice nor steals the route of the station that sent it."""
    clock, other_key = ManualClock(1_800_000_000.0), bytes(range(1, 33))
    vehicle = FakeTransport("udpout:127.0.0.1:1")
    a = FakeTransport("udpin:0.0.0.0:2", fixed=False)
    b = FakeTransport("udpin:0.0.0.0:3", fixed=False)
    router = MavlinkRouter(
        [
            RouterLink(vehicle, Role.VEHICLE, KEY),
            RouterLink(a, Role.GROUND, KEY),
            RouterLink(b, Role.GROUND, other_key),
        ],
        {
            KEY: MavlinkGuard(KEY, clock=clock, system_id=1),
            other_key: MavlinkGuard(other_key, clock=clock, system_id=1),
        },
        MavlinkGuard(KEY, clock=clock),
        signers={KEY: TimestampSource(clock), other_key: TimestampSource(clock)},
    )
    router.start()
    station_b, sink_b = signed_sender(254, other_key, clock)
    station_b.heartbeat_send(6, 8, 0, 0, 0)
    b.inject(sink_b.frames[-1], ("10.0.0.2", 14550))  # B has a receiver from now on
    station_a, sink_a = signed_sender(255, KEY, clock)
    station_a.command_long_send(0, 0, 400, 0, 1, 0, 0, 0, 0, 0, 0)  # ARM, broadcast
    a.inject(sink_a.frames[-1], ("10.0.0.1", 14550))

    def arms() -> list[bytes]:
        return [d for d, _ in vehicle.sent if parse_frame(d).msgid == 76]

    copies = [d for d, _ in b.sent if parse_frame(d).msgid == 76]
    assert len(arms()) == 1 and len(copies) == 1
    clock.advance(0.5)
    b.inject(copies[0], ("6.6.6.6", 4444))
    assert len(arms()) == 1
    # 255/190 authenticated on A: bound there, refused from B before its link id is even
    # looked at (the WRONG_DIRECTION rule for the router's own link id: test_guard)
    assert router.stats.dropped["inbound:SOURCE_BOUND"] == 1
    assert router.routes()[(255, 190)] == "udpin:0.0.0.0:2"
    router.stop()


def test_cli_router_and_simulated_vehicle_answer_a_signed_command(tmp_path: Path) -> None:
    """``mavlink-sim`` behind ``mavlink-router`` on loopback: a ground station's signed
    COMMAND_LONG reaches the simulated vehicle, its signed COMMAND_ACK comes back; the router
    logs the station's first authentication once and both print their counts on SIGTERM."""
    key_file = tmp_path / "key.hex"
    key_file.write_text(KEY.hex())
    vport, gport = free_udp_port(), free_udp_port()
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    router = subprocess.Popen(
        [sys.executable, "-m", "antireplay", "mavlink-router",
         "--vehicle", f"udpin:127.0.0.1:{vport}", "--ground", f"udpin:127.0.0.1:{gport}",
         "--key-file", str(key_file), "--store", f"sqlite:{aged_state(tmp_path / 'mav.db')}",
         "--audit", str(tmp_path / "audit.db")],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert router.stdout is not None
    started = router.stdout.readline()
    sim = subprocess.Popen(
        [sys.executable, "-m", "antireplay", "mavlink-sim", "--udp", f"127.0.0.1:{vport}",
         "--key", str(key_file), "--rate", "10"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    gcs_out = _UdpWriter(("127.0.0.1", gport))
    gcs_out.sock.settimeout(0.2)
    gcs = dialect.MAVLink(gcs_out, srcSystem=255, srcComponent=190)
    gcs.signing.secret_key, gcs.signing.sign_outgoing, gcs.signing.link_id = KEY, True, 1
    acks: list[Any] = []

    def command_acknowledged() -> bool:
        gcs.signing.timestamp = max(gcs.signing.timestamp, mav_time(SystemClock()))
        gcs.command_long_send(1, 1, dialect.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        listen_until = time.monotonic() + 0.5  # telemetry keeps coming: read for a while
        while not acks and time.monotonic() < listen_until:
            try:
                datagram = gcs_out.sock.recv(65_535)
            except TimeoutError:
                continue
            acks.extend(
                m for m in gcs.parse_buffer(datagram) or [] if m.get_type() == "COMMAND_ACK"
            )
        return bool(acks)

    try:
        if not started:  # it exited before its first line: say why
            router.wait(10)
            raise AssertionError(router.stderr.read() if router.stderr else "no stderr")
        assert started.startswith("mavlink-router vehicle udpin:") and started.endswith(
            "(system id 1)\n"
        ), started
        until("a COMMAND_ACK from the simulated vehicle", command_acknowledged, 60)
    finally:
        sim.send_signal(signal.SIGTERM)
        sim_out, sim_err = sim.communicate(timeout=30)
        router.send_signal(signal.SIGTERM)
        _, router_err = router.communicate(timeout=30)
        gcs_out.sock.close()
    assert acks[0].command == dialect.MAV_CMD_COMPONENT_ARM_DISARM
    assert acks[0].result == dialect.MAV_RESULT_ACCEPTED and acks[0].target_system == 255
    assert sim_out.startswith(
        f"mavlink-sim system 1: router option --vehicle udpin:127.0.0.1:{vport}"
    )
    assert "ack " in sim_err and "command " in sim_err and "heartbeat " in sim_err
    greeted = [line for line in router_err.splitlines() if "authenticated" in line]
    assert len(greeted) == 1 and "ground station system 255 authenticated" in greeted[0]
    assert router_err.splitlines()[-1].startswith("forwarded inbound ")


def fake_router(clock: ManualClock, store: SqliteStore, other_key: bytes) -> MavlinkRouter:
    """A vehicle, a ground link with the vehicle key and one with a key of its own, every
    guard and signer on ``store``."""

    def guard(prefix: str, key: bytes) -> MavlinkGuard:
        return MavlinkGuard(key, clock=clock, store=store, store_prefix=prefix, system_id=1)

    return MavlinkRouter(
        [
            RouterLink(FakeTransport("udpout:127.0.0.1:1"), Role.VEHICLE, KEY),
            RouterLink(FakeTransport("udpin:0.0.0.0:2", fixed=False), Role.GROUND, KEY),
            RouterLink(FakeTransport("udpin:0.0.0.0:3", fixed=False), Role.GROUND, other_key),
        ],
        {KEY: guard("in", KEY), other_key: guard("in-b", other_key)},
        MavlinkGuard(KEY, clock=clock, store=store, store_prefix="out"),
        signers={
            KEY: TimestampSource(clock, store=store, store_key="sign-a"),
            other_key: TimestampSource(clock, store=store, store_key="sign-b"),
        },
    )


def test_one_router_timer_drives_every_guards_lease_and_no_guard_has_a_thread(
    tmp_path: Path,
) -> None:
    """Three guards on a store: one timer thread for the router (no flusher per guard);
    its tick renews every lease on the router's clock."""
    clock, store = ManualClock(1_800_000_000.0), SqliteStore(tmp_path / "mav.db")
    before = {t.name for t in threading.enumerate()}
    router = fake_router(clock, store, bytes(range(1, 33)))
    router.start(wait_s=30)
    try:
        started = [t.name for t in threading.enumerate() if t.name not in before]
        assert started == ["mavlink timer"]
        guards = [*router.inbound.values(), router.outbound]
        assert all(g.claimed for g in guards)
        leases = [g.policy.lease for g in guards]
        clock.advance(1.0)
        router.tick()  # what the timer does every persist interval
        assert [g.policy.lease for g in guards] == [lease + UNITS_PER_S for lease in leases]
    finally:
        router.stop()
        store.close()
    assert [t.name for t in threading.enumerate() if t.name not in before] == []


def test_guard_start_never_sleeps_a_held_lease_is_refused_at_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``start`` claims a free lease or answers STATE_UNAVAILABLE now; waiting out a crashed
    run's lease is its owner's timer's (the router's), not a sleep in the guard."""

    def no_sleep(seconds: float) -> None:
        raise AssertionError(f"slept {seconds} s")

    clock = ManualClock(1_800_000_000.0)
    holder = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    holder.start()
    monkeypatch.setattr(time, "sleep", no_sleep)
    second = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    with pytest.raises(StateUnavailableError, match="holds the MAVLink state"):
        second.start()
    clock.advance(3)  # the holder crashed: its lease runs out on the wall clock
    second.tick()  # the owner's timer tries again
    assert second.claimed and second.restart_fence > 0


def test_a_frame_is_parsed_once_from_the_transport_to_the_vehicle(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A ground link with its own key: its guard, the router's signature with the vehicle
    key and the vehicle key's guard all share the frame its transport parsed."""
    clock, store = ManualClock(1_800_000_000.0), SqliteStore(tmp_path / "mav.db")
    other_key = bytes(range(1, 33))
    router = fake_router(clock, store, other_key)
    router.start(wait_s=30)
    parses: list[bytes] = []
    real = codec.parse_frame

    def counted(raw: bytes) -> Frame:
        parses.append(raw)
        return real(raw)

    monkeypatch.setattr(codec, "parse_frame", counted)
    monkeypatch.setattr(guard_module, "parse_frame", counted)
    try:
        station, sink = signed_sender(254, other_key, clock)
        station.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        link_b = router.links[2].transport
        assert isinstance(link_b, FakeTransport)
        link_b.inject(sink.frames[-1], ("10.0.0.2", 14550))
        vehicle = router.links[0].transport
        assert isinstance(vehicle, FakeTransport)
        assert len(vehicle.sent) == 1 and router.stats.forwarded["inbound"] == 1
        assert parses == [sink.frames[-1]]  # the transport's parse, and no other
    finally:
        router.stop()
        store.close()


# --- ids bound to a ground station's link; fences folded -------------------------------------


def station_router(
    clock: ManualClock, *, second_ground_key: bytes | None = None
) -> tuple[MavlinkRouter, FakeTransport, FakeTransport, FakeTransport, FakeTransport]:
    """A router with a vehicle, a ground link (the vehicle key), a second ground link
    (``second_ground_key``, the vehicle key if None) and a trusted link."""
    vehicle = FakeTransport("udpout:127.0.0.1:1")
    ground = FakeTransport("udpin:0.0.0.0:2", fixed=False)
    other = FakeTransport("udpin:0.0.0.0:3", fixed=False)
    trusted = FakeTransport("udpin:127.0.0.1:4", fixed=False)
    second = second_ground_key or KEY
    guards = {key: MavlinkGuard(key, clock=clock, system_id=1) for key in {KEY, second}}
    router = MavlinkRouter(
        [
            RouterLink(vehicle, Role.VEHICLE, KEY),
            RouterLink(ground, Role.GROUND, KEY),
            RouterLink(other, Role.GROUND, second),
            RouterLink(trusted, Role.TRUSTED),
        ],
        guards,
        MavlinkGuard(KEY, clock=clock),
        signers={key: TimestampSource(clock) for key in guards},
    )
    router.start()
    return router, vehicle, ground, other, trusted


def test_ids_a_ground_station_authenticated_are_refused_from_a_trusted_link() -> None:
    """A trusted link's unsigned HEARTBEAT claiming 255/190, which a ground station signed
    with its key, is refused (``SOURCE_BOUND``, reported): the route stays, and the
    vehicle's COMMAND_ACK to 255/190 still goes to the genuine station."""
    clock = ManualClock(1_800_000_000.0)
    refused: list[FrameRefusal] = []
    router, vehicle, ground, _, trusted = station_router(clock)
    router.on_reject = refused.append
    station, sink = signed_sender(255, KEY, clock)
    station.heartbeat_send(6, 8, 0, 0, 0)
    ground.inject(sink.frames[-1], ("10.0.0.1", 14550))
    trusted.inject(unsigned_heartbeat(255, 190), ("127.0.0.1", 5555))
    assert router.stats.dropped["inbound:SOURCE_BOUND"] == 1
    assert refused and refused[-1].code == "SOURCE_BOUND" and "udpin:0.0.0.0:2" in str(refused[-1])
    assert router.routes()[(255, 190)] == "udpin:0.0.0.0:2"
    autopilot, out = signed_sender(1, KEY, clock)
    autopilot.srcComponent = 1
    autopilot.command_ack_send(400, 0, 0, 0, 255, 190)
    vehicle.inject(out.frames[-1])
    acks = [(peer, parse_frame(d).msgid) for d, peer in ground.sent]
    assert (("10.0.0.1", 14550), 77) in acks
    assert not [d for d, _ in trusted.sent if parse_frame(d).msgid == 77]
    router.stop()


def test_a_ground_link_with_the_same_key_may_use_the_stations_ids() -> None:
    """The station's second radio (a ground link with the same key) is that station; a
    ground link with another key claiming its ids is refused while the station is live."""
    clock = ManualClock(1_800_000_000.0)
    router, _, ground, other, _ = station_router(clock)
    station, sink = signed_sender(255, KEY, clock)
    station.heartbeat_send(6, 8, 0, 0, 0)
    ground.inject(sink.frames[-1], ("10.0.0.1", 14550))
    clock.advance(0.01)
    station.signing.timestamp = mav_time(clock)
    station.heartbeat_send(6, 8, 0, 0, 0)
    other.inject(sink.frames[-1], ("10.0.0.9", 14550))
    assert router.stats.dropped["inbound:SOURCE_BOUND"] == 0
    router.stop()
    clock = ManualClock(1_800_000_000.0)
    router, _, ground, other, _ = station_router(clock, second_ground_key=bytes(range(1, 33)))
    station, sink = signed_sender(255, KEY, clock)
    station.heartbeat_send(6, 8, 0, 0, 0)
    ground.inject(sink.frames[-1], ("10.0.0.1", 14550))
    clock.advance(BIND_IDLE_S - 0.5)
    rival, rival_sink = signed_sender(255, bytes(range(1, 33)), clock)
    rival.heartbeat_send(6, 8, 0, 0, 0)
    other.inject(rival_sink.frames[-1], ("10.0.0.9", 14550))
    assert router.stats.dropped["inbound:SOURCE_BOUND"] == 1
    assert router.routes()[(255, 190)] == "udpin:0.0.0.0:2"
    router.stop()


def test_a_quiet_stations_ids_move_to_a_station_that_authenticates_them_elsewhere(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Failover (radio to LTE with another key, or a second station later): once the
    owning link has been quiet ``BIND_IDLE_S``, an authenticated claim elsewhere takes the
    ids (logged once) and the vehicle's answers follow; a trusted link's claim never moves
    them while the owner is live, and a live owner is never locked out by the newcomer."""
    clock = ManualClock(1_800_000_000.0)
    caplog.set_level("INFO", logger="antireplay.mavlink")
    router, vehicle, ground, other, trusted = station_router(
        clock, second_ground_key=bytes(range(1, 33))
    )
    station, sink = signed_sender(255, KEY, clock)
    station.heartbeat_send(6, 8, 0, 0, 0)
    ground.inject(sink.frames[-1], ("10.0.0.1", 14550))
    clock.advance(BIND_IDLE_S - 0.5)
    trusted.inject(unsigned_heartbeat(255, 190), ("127.0.0.1", 5555))
    assert router.stats.dropped["inbound:SOURCE_BOUND"] == 1
    clock.advance(1.0)  # the radio died: quiet BIND_IDLE_S + 0.5 s
    lte, lte_sink = signed_sender(255, bytes(range(1, 33)), clock)
    lte.heartbeat_send(6, 8, 0, 0, 0)
    other.inject(lte_sink.frames[-1], ("10.0.0.9", 14550))
    assert router.stats.dropped["inbound:SOURCE_BOUND"] == 1
    assert router.routes()[(255, 190)] == "udpin:0.0.0.0:3"
    moved = [r.getMessage() for r in caplog.records if "moved from link" in r.getMessage()]
    assert moved == [
        "ids 255/190 moved from link udpin:0.0.0.0:2 (quiet 5.5 s) to link udpin:0.0.0.0:3, "
        "authenticated"
    ]
    autopilot, out = signed_sender(1, KEY, clock)
    autopilot.srcComponent = 1
    autopilot.command_ack_send(400, 0, 0, 0, 255, 190)
    vehicle.inject(out.frames[-1])
    assert [peer for d, peer in other.sent if parse_frame(d).msgid == 77] == [("10.0.0.9", 14550)]
    clock.advance(0.1)  # the old radio, live again, is now the other station
    station.signing.timestamp = mav_time(clock)
    station.heartbeat_send(6, 8, 0, 0, 0)
    ground.inject(sink.frames[-1], ("10.0.0.1", 14550))
    assert router.stats.dropped["inbound:SOURCE_BOUND"] == 2
    router.stop()


def test_a_trusted_link_cannot_claim_another_component_of_a_live_stations_system() -> None:
    """A station authenticated as 255/190: a trusted link claiming 255/0 or 255/191 is
    refused (no route, no copies to system 255); a vehicle's other components and a
    station of another key on another component of 255 are not."""
    clock = ManualClock(1_800_000_000.0)
    router, vehicle, ground, other, trusted = station_router(
        clock, second_ground_key=bytes(range(1, 33))
    )
    station, sink = signed_sender(255, KEY, clock)
    station.heartbeat_send(6, 8, 0, 0, 0)
    ground.inject(sink.frames[-1], ("10.0.0.1", 14550))
    for component in (0, 191):
        trusted.inject(unsigned_heartbeat(255, component), ("127.0.0.1", 5555))
    assert router.stats.dropped["inbound:SOURCE_BOUND"] == 2
    assert set(router.routes()) == {(255, 190)}
    observer, observer_sink = signed_sender(255, bytes(range(1, 33)), clock)
    observer.srcComponent = 191
    observer.heartbeat_send(6, 8, 0, 0, 0)
    other.inject(observer_sink.frames[-1], ("10.0.0.9", 14550))
    autopilot, out = signed_sender(1, KEY, clock)
    for component in (1, 100):
        autopilot.srcComponent = component
        autopilot.heartbeat_send(2, 3, 0, 0, 0)
        vehicle.inject(out.frames[-1])
    assert router.stats.dropped["inbound:SOURCE_BOUND"] == 2
    assert {(255, 191), (1, 1), (1, 100)} <= set(router.routes())
    router.stop()


def test_refusals_behind_the_fence_are_said_once_then_one_line_per_interval() -> None:
    """A router on a memory store is fenced for ``max_forward_s``: 200 frames behind the
    fence are each counted, but reported as the first, then one summary per interval with
    how many and from how many senders; the fence passed, the router says so (None)."""
    clock = ManualClock(1_800_000_000.0)
    store = MemoryStore(clock=clock)
    vehicle = FakeTransport("udpout:127.0.0.1:1")
    ground = FakeTransport("udpin:0.0.0.0:2", fixed=False)
    guard = MavlinkGuard(KEY, clock=clock, store=store, system_id=1, max_forward_s=20)
    router = MavlinkRouter(
        [RouterLink(vehicle, Role.VEHICLE, KEY), RouterLink(ground, Role.GROUND, KEY)],
        {KEY: guard},
        MavlinkGuard(KEY, clock=clock, store=store, store_prefix="out", max_forward_s=20),
        signers={KEY: TimestampSource(clock)},
    )
    refused: list[FrameRefusal] = []
    router.on_reject = refused.append
    router.start()
    fence = router.fence()
    assert fence is not None and fence[1] == "lost"
    assert fence[0] == pytest.approx(clock.wall() + 20, abs=0.01)
    senders = [signed_sender(system, KEY, clock) for system in (200, 201)]
    for i in range(200):
        mav, sink = senders[i % 2]
        mav.signing.timestamp = mav_time(clock)
        mav.heartbeat_send(6, 8, 0, 0, 0)
        ground.inject(sink.frames[-1], ("10.0.0.1", 14550 + i % 2))
    assert router.stats.dropped["inbound:MESSAGE_STALE"] == 200
    assert len(refused) == 200 and sum(r.folded for r in refused) == 199  # a hook sees each
    said = [r for r in refused if not r.folded]  # what the log and the audit trail get
    (first,) = said
    assert "restart fence" in first.reason and "summarised every 5 s" in first.reason
    clock.advance(6)  # the timer, an interval later (the fence holds 14 s more)
    router.tick()
    said = [r for r in refused if not r.folded]
    assert len(said) == 2 and said[1].frames == 199
    assert "from 2 senders (claimed ids" in str(said[1]) and str(said[1]).startswith("refused 199")
    clock.advance(15)
    assert router.fence() is None
    router.stop()
    assert len([r for r in refused if not r.folded]) == 2


def test_a_sender_whose_clock_lags_past_the_fence_is_folded_and_told_so() -> None:
    """The fence passed by the router's clock, a sender 12 s behind is still below it for
    11 s: its 110 refusals are said as the first, then one line per interval (not one a
    second), and each says what is true: its clock is behind, or these are captures."""
    clock = ManualClock(1_800_000_000.0)
    store = MemoryStore(clock=clock)
    vehicle = FakeTransport("udpout:127.0.0.1:1")
    ground = FakeTransport("udpin:0.0.0.0:2", fixed=False)
    guard = MavlinkGuard(KEY, clock=clock, store=store, system_id=1, max_forward_s=20)
    router = MavlinkRouter(
        [RouterLink(vehicle, Role.VEHICLE, KEY), RouterLink(ground, Role.GROUND, KEY)],
        {KEY: guard},
        MavlinkGuard(KEY, clock=clock, store=store, store_prefix="out", max_forward_s=20),
        signers={KEY: TimestampSource(clock)},
    )
    refused: list[FrameRefusal] = []
    router.on_reject = refused.append
    router.start()
    clock.advance(21)
    assert router.fence() is None
    mav, sink = signed_sender(255, KEY, clock)
    for _ in range(110):
        mav.signing.timestamp = mav_time(clock) - 12 * UNITS_PER_S
        mav.heartbeat_send(6, 8, 0, 0, 0)
        ground.inject(sink.frames[-1], ("10.0.0.1", 14550))
        clock.advance(0.1)
        router.tick()
    assert router.stats.dropped["inbound:MESSAGE_STALE"] == 110
    said = [r for r in refused if not r.folded]
    assert len(said) == 3, [str(r) for r in said]  # the first, then at 5 s and 10 s
    assert "sender 255/190's clock is behind, or this is a capture" in said[0].reason
    assert "fenced" not in said[0].reason
    assert [round(r.frames, -1) for r in said[1:]] == [50, 50]
    assert "sender 255/190's timestamps are 10.9 s below the restart fence" in said[1].reason
    assert "its clock is behind, or these are captures" in said[1].reason
    router.stop()
    said = [r for r in refused if not r.folded]
    assert len(said) == 4 and sum(r.frames for r in said) == 110  # the rest, at stop


class WriteLog:
    """A store wrapper that records every ``advance`` (a store write): its key, and whether
    the frame path made it (not the timer thread, not an explicit tick)."""

    def __init__(self, inner: SqliteStore) -> None:
        self.inner = inner
        self.ticking = False
        self.frame_path: list[str] = []
        self.timer: list[str] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def advance(self, key: str, value: int) -> bool:
        timer = self.ticking or threading.current_thread().name == "mavlink timer"
        (self.timer if timer else self.frame_path).append(key)
        return self.inner.advance(key, value)


def test_a_burst_verified_and_signed_on_behalf_writes_the_store_only_from_the_timer(
    tmp_path: Path,
) -> None:
    """5,000 signed frames from a ground station and 5,000 unsigned ones signed on a trusted
    tool's behalf, 5,000 a second on the router's clock with its timer ticking every half
    second: every frame forwarded, and no store write on the frame path (leases, stream
    high-waters and the signer's timestamp ceiling are the timer's, a handful per second)."""
    clock = ManualClock(1_800_000_000.0)
    store = WriteLog(SqliteStore(aged_state(tmp_path / "mav.db", clock), clock=clock))

    def guard(prefix: str) -> MavlinkGuard:
        return MavlinkGuard(KEY, clock=clock, store=store, store_prefix=prefix, system_id=1)

    vehicle = FakeTransport("udpout:127.0.0.1:1")
    ground = FakeTransport("udpin:0.0.0.0:2", fixed=False)
    trusted = FakeTransport("udpin:0.0.0.0:3", fixed=False)
    router = MavlinkRouter(
        [
            RouterLink(vehicle, Role.VEHICLE, KEY),
            RouterLink(ground, Role.GROUND, KEY),
            RouterLink(trusted, Role.TRUSTED),
        ],
        {KEY: guard("in")},
        guard("out"),
        signers={KEY: TimestampSource(clock, store=store, store_key="sign")},
    )
    router.start(wait_s=30)
    station, sink = signed_sender(255, KEY, clock)
    tool = dialect.MAVLink(Sink(), srcSystem=254, srcComponent=190)
    try:
        for i in range(5_000):
            station.command_long_send(1, 1, 400, 0, i, 0, 0, 0, 0, 0, 0)
            ground.inject(sink.frames[-1], ("10.0.0.2", 14550))
            tool.command_long_send(1, 1, 400, 0, i, 0, 0, 0, 0, 0, 0)
            trusted.inject(tool.file.frames[-1], ("127.0.0.1", 5760))
            clock.advance(0.0002)
            if i % 2_500 == 2_499:
                store.ticking = True
                router.tick()  # what the timer does every half second of this clock
                store.ticking = False
        assert router.stats.forwarded["inbound"] == 10_000 and not router.stats.dropped
        assert len(vehicle.sent) == 10_000
        assert store.frame_path == []
        assert "sign" in store.timer and len(store.timer) <= 20  # a few per tick
    finally:
        router.stop()
        store.close()
