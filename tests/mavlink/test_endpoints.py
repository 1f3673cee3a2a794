"""MAVLink endpoints and routing: connection strings, TCP links, per-link keys, allow-lists."""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

os.environ["MAVLINK20"] = "1"  # pymavlink's mavutil speaks MAVLink 1 unless told otherwise
from pymavlink import mavutil

from antireplay.core.clock import SystemClock
from antireplay.mavlink import (
    FrameRefusal,
    MavlinkGuard,
    MavlinkRouter,
    Role,
    RouterLink,
    TimestampSource,
    open_transport,
    parse_endpoint,
    passphrase_key,
)
from antireplay.mavlink.codec import Frame, FrameReader, mav_time
from antireplay.mavlink.endpoints import (
    LOG_EVERY_S,
    Peer,
    TcpServerTransport,
    Transport,
)
from antireplay.wiring import router_metrics
from harness import free_port, until
from harness.mavlink_frames import (
    KEY,
    command_frame,
    encoder,
    unsigned_heartbeat,
    v1_radio_status,
)

RADIO_KEY = passphrase_key("the radio link's own passphrase")


class Net:
    """A vehicle (pymavlink, udpin, key KEY) behind a router with a ground endpoint."""

    def __init__(
        self,
        ground: str,
        ground_key: bytes = KEY,
        from_vehicle: frozenset[int] = frozenset(),
        v1: frozenset[int] = frozenset(),
        vehicle_over: str = "udp",
    ) -> None:
        vport = free_port()
        self.vehicle = mavutil.mavlink_connection(
            f"{vehicle_over}in:127.0.0.1:{vport}", source_system=1, source_component=1
        )
        to_vehicle = f"{vehicle_over}{'out' if vehicle_over == 'udp' else ''}:127.0.0.1:{vport}"
        self.vehicle.setup_signing(KEY, sign_outgoing=True, link_id=7)
        self.refused: list[FrameRefusal] = []
        keys = {KEY, ground_key}
        self.ground = RouterLink(open_transport(parse_endpoint(ground)), Role.GROUND, ground_key)
        vehicle = RouterLink(open_transport(parse_endpoint(to_vehicle)), Role.VEHICLE, KEY)

        self.router = MavlinkRouter(
            [vehicle, self.ground],
            {key: MavlinkGuard(key, system_id=1) for key in keys},
            MavlinkGuard(KEY, allow_unsigned=from_vehicle, allow_v1=v1),
            signers={key: TimestampSource() for key in keys},
            on_reject=self.refused.append,
        )
        self.router.start()
        self.port = self.ground.transport.address[1]

    def vehicle_sends(self, send: Callable[[Any], None], until_seen: Callable[[], object]) -> None:
        """Send from the vehicle until ``until_seen`` (the vehicle's first frames may race
        the router's startup; every send is a fresh, signed frame)."""
        deadline = time.monotonic() + 20
        while not until_seen():
            if time.monotonic() > deadline:
                pytest.fail("the vehicle's frames never arrived")
            send(self.vehicle.mav)
            time.sleep(0.02)

    def ground_station(self) -> Any:
        """A GCS on the ground port, signing with KEY, heard by the vehicle (so that the
        vehicle knows where to answer); RADIO_STATUS may come to it unsigned."""
        gcs = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{self.port}", source_system=255, source_component=190
        )
        gcs.setup_signing(KEY, sign_outgoing=True, link_id=2, allow_unsigned_callback=radio_ok)
        gcs.mav.heartbeat_send(6, 8, 0, 0, 0)
        assert self.vehicle.recv_match(type="HEARTBEAT", blocking=True, timeout=20) is not None
        return gcs

    def close(self) -> None:
        self.router.stop()
        self.vehicle.close()


@pytest.fixture
def tcp_net() -> Iterator[Net]:
    net = Net("tcpin:127.0.0.1:0", ground_key=RADIO_KEY)
    yield net
    net.close()


def heartbeat_from(conn: Any, system: int) -> Callable[[], bool]:
    def check() -> bool:
        msg = conn.recv_match(type="HEARTBEAT", blocking=False)
        return msg is not None and msg.get_srcSystem() == system

    return check


def test_tcp_ground_link_with_its_own_key(tcp_net: Net) -> None:
    """A GCS on ``tcpin`` signing with its link's passphrase key: its command reaches the
    vehicle signed with the vehicle key; telemetry reaches it signed with its own key, and
    never a client that has not authenticated."""
    gcs = mavutil.mavlink_connection(
        f"tcp:127.0.0.1:{tcp_net.port}", source_system=255, source_component=190
    )
    idle = socket.create_connection(("127.0.0.1", tcp_net.port))
    try:
        gcs.setup_signing(RADIO_KEY, sign_outgoing=True, link_id=2)
        gcs.mav.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        command = tcp_net.vehicle.recv_match(type="COMMAND_LONG", blocking=True, timeout=20)
        assert command is not None and command.get_signed() and command.get_link_id() == 251
        assert command.get_srcSystem() == 255  # verified by the vehicle with KEY
        seen: list[Any] = []

        def heartbeat_at_gcs() -> bool:
            msg = gcs.recv_match(type="HEARTBEAT", blocking=False)
            if msg is not None and msg.get_srcSystem() == 1:
                seen.append(msg)
            return len(seen) >= 2

        tcp_net.vehicle_sends(lambda mav: mav.heartbeat_send(2, 3, 0, 0, 4), heartbeat_at_gcs)
        assert seen[0].get_signed() and seen[0].get_link_id() == 251  # signed again, RADIO_KEY
        idle.setblocking(False)
        with pytest.raises(BlockingIOError):
            idle.recv(4096)  # the client that never authenticated got nothing
    finally:
        gcs.close()
        idle.close()


def radio_ok(_mav: object, msgid: int) -> bool:
    """A GCS's hook, as MAVProxy's: RADIO_STATUS may come unsigned."""
    return msgid == 109


@pytest.mark.parametrize("listed", [False, True])
def test_v1_radio_status_from_the_vehicle_side_only_where_listed(listed: bool) -> None:
    net = Net(
        "udpin:127.0.0.1:0", from_vehicle=frozenset({109}), v1=frozenset({109} if listed else ())
    )
    gcs = net.ground_station()
    try:
        radio = v1_radio_status()
        net.vehicle.write(radio)  # the vehicle answers the address the router sends from
        if listed:
            until("the v1 RADIO_STATUS at the GCS", lambda: gcs.recv_match(type="RADIO_STATUS"))
        else:
            until("the v1 RADIO_STATUS refused", lambda: net.refused)
            assert net.refused[0].raw == radio and "v1" in net.refused[0].reason
    finally:
        gcs.close()
        net.close()


def test_targeted_frame_from_the_vehicle_to_an_unknown_system_is_no_route() -> None:
    net = Net("udpin:127.0.0.1:0")
    gcs = net.ground_station()
    try:
        net.vehicle.mav.command_long_send(99, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        until("the command refused", lambda: net.refused)
        assert (net.refused[0].code, net.refused[0].reason) == ("NO_ROUTE", "target never seen")
        assert str(net.refused[0]).startswith("refused outbound frame on udpout:127.0.0.1:")
    finally:
        gcs.close()
        net.close()


def test_vehicle_over_tcp_as_sitl_offers_it() -> None:
    """The vehicle as a TCP server (SITL's tcp:5760), the router connecting to it."""
    net = Net("udpin:127.0.0.1:0", vehicle_over="tcp")
    gcs = mavutil.mavlink_connection(
        f"udpout:127.0.0.1:{net.port}", source_system=255, source_component=190
    )
    try:
        gcs.setup_signing(KEY, sign_outgoing=True, link_id=2)
        got: list[Any] = []

        def command_at_vehicle() -> bool:
            gcs.mav.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)  # until connected
            msg = net.vehicle.recv_match(type="COMMAND_LONG", blocking=True, timeout=0.2)
            got.extend([msg] if msg is not None else [])
            return bool(got)

        until("a command over the router's TCP connection", command_at_vehicle)
        assert got[0].get_signed() and got[0].get_srcSystem() == 255
        net.vehicle_sends(lambda mav: mav.heartbeat_send(2, 3, 0, 0, 4), heartbeat_from(gcs, 1))
    finally:
        gcs.close()
        net.close()


class Delivered:
    """A transport's ``deliver``: what it handed over (parsed once: each frame's bytes here),
    frame by frame, with the peer."""

    def __init__(self) -> None:
        self.frames: list[tuple[Peer | None, bytes]] = []
        self.skipped: list[int] = []  # the bytes dropped, one entry per hand-over that had some

    def __call__(self, _t: Transport, peer: Peer | None, frames: list[Frame], skipped: int) -> None:
        assert all(isinstance(frame, Frame) for frame in frames)
        self.frames.extend((peer, frame.raw) for frame in frames)
        if skipped:
            self.skipped.append(skipped)


def test_a_datagram_is_whole_frames_or_dropped_whole() -> None:
    """UDP: a datagram that is not exactly whole frames hands over no frame, and all of
    its bytes as dropped; a datagram of two whole frames hands over both."""
    mav, sink = encoder()
    frames = [command_frame(mav, sink, param1=float(i)) for i in range(6)]
    bad = [b"\x00" + frames[0], frames[1] + b"\xfd\x01", frames[2][:-1]]
    transport = open_transport(parse_endpoint("udpin:127.0.0.1:0"))
    delivered = Delivered()
    transport.start(delivered)
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for datagram in [*bad, frames[3] + frames[4], frames[5]]:
            sender.sendto(datagram, transport.address)
        until("the last datagram", lambda: frames[5] in (f for _, f in delivered.frames))
        assert [f for _, f in delivered.frames] == frames[3:]
        assert delivered.skipped == [len(datagram) for datagram in bad]
    finally:
        sender.close()
        transport.close()


def test_a_stream_resynchronises_past_leading_garbage() -> None:
    """TCP (as serial): bytes before a frame are skipped and counted, the frame passes."""
    mav, sink = encoder()
    frame = command_frame(mav, sink)
    transport = open_transport(parse_endpoint("tcpin:127.0.0.1:0"))
    delivered = Delivered()
    transport.start(delivered)
    try:
        with socket.create_connection(transport.address) as client:
            client.sendall(b"\x00garbage" + frame)
            until("the frame", lambda: delivered.frames)
        assert [f for _, f in delivered.frames] == [frame]
        assert delivered.skipped == [8]
    finally:
        transport.close()


def _thread_cpu_s(thread: threading.Thread) -> float:
    assert thread.ident is not None
    return time.clock_gettime(time.pthread_getcpuclockid(thread.ident))


def _new_pty(link: Path) -> tuple[int, int]:
    """A pty pair whose slave ``link`` names (as udev's /dev/serial/by-id/ links do);
    the master does not block (nothing reads its echo)."""
    master, slave = os.openpty()
    os.set_blocking(master, False)
    staged = link.with_name("staged")
    staged.symlink_to(os.ttyname(slave))
    staged.replace(link)
    return master, slave


def test_serial_device_that_goes_away_is_reopened_without_spinning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A flight controller that reboots closes its port: the reader counts one end of file,
    logs it, closes the device and waits (no busy loop) until it comes back, then reads on."""
    caplog.set_level(logging.INFO, logger="antireplay.mavlink")
    device = tmp_path / "ttyFC"
    master, slave = _new_pty(device)
    transport = open_transport(parse_endpoint(f"{device},115200"))
    delivered = Delivered()
    transport.start(delivered)
    frame = unsigned_heartbeat(1)
    second: tuple[int, int] | None = None
    try:
        os.write(master, frame)
        until("the first frame", lambda: delivered.frames == [(None, frame)])
        os.close(master)
        os.close(slave)
        until("the end of file", lambda: transport.errors["eof"])
        cpu = _thread_cpu_s(transport._threads[0])
        until("four reopen attempts", lambda: transport.errors["reopen"] >= 4)  # 0.75 s
        assert _thread_cpu_s(transport._threads[0]) - cpu < 0.1  # waiting, not spinning
        assert transport.errors["eof"] == 1  # the closed device is not read again
        assert not transport.send(frame, None)
        assert transport.errors["not_connected"] == 1
        second = _new_pty(device)

        def arrived() -> bool:
            with contextlib.suppress(BlockingIOError):  # the first may go before raw mode
                os.write(second[0], frame)
            return len(delivered.frames) > 1

        until("a frame from the device that came back", arrived)
        assert transport.send(frame, None)
        lines = [r.getMessage() for r in caplog.records]
        assert sum(": eof: " in line for line in lines) == 1
        assert sum(": reopen: " in line for line in lines) == 1  # the rest rate-limited
        assert f"{device},115200: opened again" in lines
    finally:
        transport.close()
        for fd in second or ():
            os.close(fd)


def _stall(client: socket.socket, send: Callable[[bytes], bool], frame: bytes) -> float:
    """Send ``frame`` to a peer that reads nothing until a send fails; how long the
    failing send took."""
    for _ in range(1_000_000):
        start = time.perf_counter()
        if not send(frame):
            return time.perf_counter() - start
    pytest.fail(f"{client} took every frame")


def _stream_to_end(sock: socket.socket) -> FrameReader:
    """Read ``sock`` to its end through a FrameReader (what a GCS's parser makes of it)."""
    reader = FrameReader()
    sock.settimeout(20)
    while data := sock.recv(65_536):
        reader.feed(data)
    return reader


def test_tcpin_client_that_does_not_read_is_dropped_without_blocking_the_sender() -> None:
    """The router's send runs in another link's reader thread: a full client is never
    waited for; it is disconnected (counted as stalled) and never gets a frame spliced
    into another: at most a cut-short last one before the end of the stream."""
    transport = open_transport(parse_endpoint("tcpin:127.0.0.1:0"))
    delivered = Delivered()
    transport.start(delivered)
    client = socket.socket()
    client.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    client.connect(transport.address)
    try:
        client.sendall(unsigned_heartbeat(255))
        until("the client's frame", lambda: delivered.frames)
        peer = delivered.frames[0][0]
        big = command_frame(*encoder())
        took = _stall(client, lambda frame: transport.send(frame, peer), big)
        assert took < 0.15  # the old sendall waited out its 0.2 s timeout here
        assert transport.errors == Counter({"stalled": 1})
        reader = _stream_to_end(client)  # the server hung up
        assert reader.skipped == 0 and reader.pending < len(big)
        assert not transport.send(big, peer)
        assert transport.errors["not_connected"] == 1
    finally:
        client.close()
        transport.close()


def test_tcp_vehicle_that_does_not_read_is_dropped_and_reconnected() -> None:
    """``tcp:`` (the router as SITL's client): a server that stops reading is hung up on,
    never waited for, and connected to again."""
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(20)
    transport = open_transport(parse_endpoint(f"tcp:127.0.0.1:{server.getsockname()[1]}"))
    transport.start(Delivered())
    first, _ = server.accept()
    try:
        until("connected", lambda: transport.send(unsigned_heartbeat(1), None))
        took = _stall(first, lambda frame: transport.send(frame, None), command_frame(*encoder()))
        assert took < 0.15
        assert transport.errors["stalled"] == 1
        reader = _stream_to_end(first)
        assert reader.skipped == 0
        second, _ = server.accept()  # it came back
        second.close()
    finally:
        first.close()
        server.close()
        transport.close()


def _hung_up(sock: socket.socket) -> bool:
    sock.settimeout(20)
    with contextlib.suppress(ConnectionResetError):
        return sock.recv(1) == b""
    return True


def test_full_tcpin_evicts_the_oldest_client_that_never_authenticated(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Idle connections cannot lock ground stations out: a newcomer to a full ``tcpin``
    takes the slot of the oldest client that never sent a frame the router accepted;
    when every client authenticated, the newcomer is refused.  All of it is counted in
    the router's metrics and logged once per kind."""
    ground = RouterLink(
        TcpServerTransport(parse_endpoint("tcpin:127.0.0.1:0"), max_clients=2), Role.GROUND, KEY
    )
    vehicle = RouterLink(open_transport(parse_endpoint("udpout:127.0.0.1:9")), Role.VEHICLE, KEY)
    router = MavlinkRouter([ground, vehicle], {KEY: MavlinkGuard(KEY)}, MavlinkGuard(KEY))
    router.start()
    address = ground.transport.address
    now = mav_time(SystemClock())
    clients: list[socket.socket] = []

    def connect() -> socket.socket:
        clients.append(socket.create_connection(address))
        return clients[-1]

    def authenticate(sock: socket.socket, sysid: int) -> None:
        mav, sink = encoder(sysid, ts=now)
        mav.heartbeat_send(6, 8, 0, 0, 0)
        sock.sendall(sink.frames[-1])

    try:
        with caplog.at_level(logging.WARNING, logger="antireplay.mavlink"):
            authenticate(connect(), 250)
            until("the first GCS authenticated", lambda: len(ground.peers) == 1)
            idle, newcomer = connect(), connect()
            assert _hung_up(idle)  # the oldest unauthenticated client gave its slot
            authenticate(newcomer, 251)
            until("the newcomer authenticated", lambda: len(ground.peers) == 2)
            late = connect()
            assert _hung_up(late)  # every slot authenticated: refused
            assert not _hung_up_now(clients[0]) and not _hung_up_now(newcomer)
        errors = ground.transport.errors
        assert (errors["clients_evicted"], errors["clients_refused"]) == (1, 1)
        exported = {
            (sample.labels["endpoint"], sample.labels["kind"]): sample.value
            for family in router_metrics(router)
            if family.name == "antireplay_mavlink_transport_errors"
            for sample in family.samples
        }
        assert exported == {
            (ground.name, "clients_evicted"): 1.0,
            (ground.name, "clients_refused"): 1.0,
        }
        lines = [r.getMessage() for r in caplog.records]
        assert sum("clients_evicted" in line for line in lines) == 1
        assert sum("clients_refused" in line for line in lines) == 1
    finally:
        for sock in clients:
            sock.close()
        router.stop()


def _hung_up_now(sock: socket.socket) -> bool:
    sock.setblocking(False)
    try:
        return sock.recv(1) == b""
    except BlockingIOError:
        return False


def test_transport_errors_are_logged_first_then_rate_limited(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """One line for the first error of a kind; later ones are counted, and the next line
    (after ``LOG_EVERY_S``) says how many it left out."""
    transport = Transport(parse_endpoint("udpout:127.0.0.1:9"))
    with caplog.at_level(logging.WARNING, logger="antireplay.mavlink"):
        for _ in range(3):
            transport._error("send", "refused")
        transport._logged["send"] = (time.monotonic() - LOG_EVERY_S, 1)  # a minute later
        transport._error("send", "refused")
    assert [r.getMessage() for r in caplog.records] == [
        "udpout:127.0.0.1:9: send: refused",
        "udpout:127.0.0.1:9: send: refused (2 more since the last line)",
    ]
    assert transport.errors["send"] == 4
