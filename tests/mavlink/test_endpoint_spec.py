"""MAVLink connection strings: their grammar, and which endpoints only this host reaches."""

from __future__ import annotations

import socket
from typing import Any

import pytest

from antireplay.mavlink.endpoint_spec import EndpointSpec, addresses, is_local, parse_endpoint


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


@pytest.mark.parametrize(
    ("text", "local"),
    [
        ("udpin:127.0.0.1:14551", True),
        ("udpout:127.0.0.2:14551", True),
        ("tcpin:localhost:5760", True),
        ("tcp:[::1]:5760", True),
        ("/dev/ttyACM0,115200", True),
        ("udpin:0.0.0.0:14551", False),
        ("tcpin:192.0.2.2:5760", False),
        ("udpout:192.0.2.77:14550", False),
        ("udpin:gcs.example:14550", False),  # a name may resolve anywhere
    ],
)
def test_only_loopback_and_serial_endpoints_are_local(text: str, local: bool) -> None:
    """A trusted endpoint must be local (the router signs on its behalf) unless acknowledged."""
    assert is_local(parse_endpoint(text)) is local


@pytest.mark.parametrize(
    ("answers", "local"),
    [
        (["127.0.0.1", "::1"], True),
        (["192.0.2.2"], False),  # /etc/hosts or DNS maps localhost to the LAN
        (["127.0.0.1", "192.0.2.2"], False),  # every address must be loopback
        ([], False),  # does not resolve
    ],
)
def test_a_name_is_local_only_if_every_address_it_resolves_to_is_loopback(
    monkeypatch: pytest.MonkeyPatch, answers: list[str], local: bool
) -> None:
    def resolve(host: str, port: int, *args: object, **kwargs: object) -> list[Any]:
        if not answers:
            raise socket.gaierror(-2, "Name or service not known")
        return [
            (socket.AF_INET6 if ":" in a else socket.AF_INET, socket.SOCK_STREAM, 6, "", (a, port))
            for a in answers
        ]

    monkeypatch.setattr(socket, "getaddrinfo", resolve)
    spec = parse_endpoint("tcpin:localhost:5760")
    assert is_local(spec) is local
    assert addresses(spec) == tuple(answers)
