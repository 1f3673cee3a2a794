"""MAVLink connection strings: the endpoints MAVLink users type, and whether they are local.

Theory of operation
-------------------
:func:`parse_endpoint` reads the syntax of pymavlink's ``mavutil`` and MAVProxy's
``--master``/``--out``: ``udpin:HOST:PORT`` (bind and answer whoever sent),
``udpout:HOST:PORT`` (send to a fixed address), ``udp:HOST:PORT`` (mavutil's
alias of ``udpin``), ``tcp:HOST:PORT`` (connect, reconnecting), ``tcpin:HOST:PORT``
(listen; each client is a peer) and a serial device ``/dev/ttyACM0,57600``
(MAVProxy's ``DEVICE,BAUD``; ``DEVICE:BAUD`` as mavlink-router writes it, or a
bare device at 57,600 baud, MAVProxy's default); a string that is none of these is a
``ValueError`` saying what was expected.  :func:`is_local` says whether only this host
reaches an endpoint (loopback or serial): a router's trusted endpoints must be, since
it signs on their behalf.  Nothing here opens a socket; :func:`addresses` resolves a
name (getaddrinfo), and :mod:`.endpoints` opens the transports.
"""

from __future__ import annotations

import ipaddress
import socket
import termios
from dataclasses import dataclass

DEFAULT_BAUD = 57_600


@dataclass(frozen=True)
class EndpointSpec:
    """One parsed connection string; ``text`` names the link in logs, metrics and key files."""

    text: str
    kind: str  # udpin, udpout, tcp, tcpin, serial
    host: str  # the device, for serial
    port: int  # the baud rate, for serial


def parse_endpoint(text: str) -> EndpointSpec:
    """Parse a mavutil/MAVProxy connection string (module docstring); ValueError if not one."""
    scheme, sep, rest = text.partition(":")
    if sep and scheme in {"udp", "udpin", "udpout", "tcp", "tcpin"}:
        host, _, port = rest.rpartition(":")
        if not host or not (port.isascii() and port.isdigit()) or int(port) > 65_535:
            raise ValueError(f"{text!r}: expected {scheme}:HOST:PORT with PORT 0..65535")
        return EndpointSpec(text, "udpin" if scheme == "udp" else scheme, host, int(port))
    if not text.startswith("/") and not text.upper().startswith("COM"):
        raise ValueError(
            f"{text!r}: expected udpin:, udpout:, tcp:, tcpin:HOST:PORT or a serial DEVICE,BAUD"
        )
    device, baud = text, str(DEFAULT_BAUD)
    for separator in (",", ":"):
        if separator in text:
            device, _, baud = text.rpartition(separator)
            break
    if not (baud.isascii() and baud.isdigit()) or not hasattr(termios, f"B{int(baud)}"):
        raise ValueError(f"{text!r}: {baud!r} is not a baud rate this system supports")
    return EndpointSpec(text, "serial", device, int(baud))


def is_local(spec: EndpointSpec) -> bool:
    """Whether only this host reaches the endpoint: a serial device, or a host whose every
    address is loopback (``127.0.0.0/8``, ``::1``; a name such as ``localhost`` is resolved,
    since /etc/hosts or DNS may map it to the LAN).  A router signs on a trusted endpoint's
    behalf, so one that is not local must be acknowledged by the operator."""
    if spec.kind == "serial":
        return True
    found = addresses(spec)
    return bool(found) and all(ipaddress.ip_address(a).is_loopback for a in found)


def addresses(spec: EndpointSpec) -> tuple[str, ...]:
    """The IP addresses a network endpoint's host is (a literal) or resolves to
    (getaddrinfo); empty if it does not resolve."""
    host = spec.host.strip("[]")
    try:
        return (str(ipaddress.ip_address(host)),)
    except ValueError:
        pass
    try:
        found = socket.getaddrinfo(host, spec.port, proto=socket.IPPROTO_TCP)
    except (OSError, UnicodeError):
        return ()
    return tuple(dict.fromkeys(str(info[4][0]).split("%")[0] for info in found))
