"""MAVLink endpoints and routing: connection strings, TCP links, per-link keys, allow-lists."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

os.environ["MAVLINK20"] = "1"  # pymavlink's mavutil speaks MAVLink 1 unless told otherwise
from pymavlink import mavutil

from antireplay.mavlink import (
    EndpointSpec,
    Link,
    MavlinkGuard,
    MavlinkRouter,
    Refusal,
    Role,
    TimestampSource,
    open_transport,
    parse_endpoint,
    passphrase_key,
)
from tests.harness import free_port, until
from tests.mavlink_frames import KEY
from tests.test_mavlink_codec import v1_radio_status

RADIO_KEY = passphrase_key("the radio link's own passphrase")


@pytest.mark.parametrize(
    ("text", "kind", "host", "port"),
    [
        ("udpin:0.0.0.0:14550", "udpin", "0.0.0.0", 14550),
        ("udp:127.0.0.1:14550", "udpin", "127.0.0.1", 14550),  # mavutil: udp is udpin
        ("udpout:10.0.0.2:14550", "udpout", "10.0.0.2", 14550),
        ("tcp:127.0.0.1:5760", "tcp", "127.0.0.1", 5760),
        ("tcpin:0.0.0.0:5760", "tcpin", "0.0.0.0", 5760),
        ("/dev/ttyACM0,921600", "serial", "/dev/ttyACM0", 921_600),  # MAVProxy
        (
            "/dev/serial/by-id/usb-ArduPilot:57600",
            "serial",
            "/dev/serial/by-id/usb-ArduPilot",
            57_600,
        ),
        ("/dev/ttyUSB0", "serial", "/dev/ttyUSB0", 57_600),  # MAVProxy's default baud
    ],
)
def test_connection_strings(text: str, kind: str, host: str, port: int) -> None:
    assert parse_endpoint(text) == EndpointSpec(text, kind, host, port)


@pytest.mark.parametrize(
    "text", ["udpin:14550", "tcp:host:99999", "serial0", "/dev/ttyACM0,1234", "udpbcast:1.2.3.4:5"]
)
def test_bad_connection_strings_say_what_was_expected(text: str) -> None:
    with pytest.raises(ValueError, match=r"expected|baud"):
        parse_endpoint(text)


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
        self.refused: list[Refusal] = []
        keys = {KEY, ground_key}
        self.ground = Link(open_transport(parse_endpoint(ground)), Role.GROUND, ground_key)
        vehicle = Link(open_transport(parse_endpoint(to_vehicle)), Role.VEHICLE, KEY)

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
