"""MAVLink endpoints: the connection strings MAVLink users type, and their transports.

Theory of operation
-------------------
:func:`parse_endpoint` reads the syntax of pymavlink's ``mavutil`` and MAVProxy's
``--master``/``--out``: ``udpin:HOST:PORT`` (bind and answer whoever sent),
``udpout:HOST:PORT`` (send to a fixed address), ``udp:HOST:PORT`` (mavutil's
alias of ``udpin``), ``tcp:HOST:PORT`` (connect, reconnecting), ``tcpin:HOST:PORT``
(listen; each client is a peer) and a serial device ``/dev/ttyACM0,57600``
(MAVProxy's ``DEVICE,BAUD``; ``DEVICE:BAUD`` as mavlink-router writes it, or a
bare device at 57,600 baud, MAVProxy's default).

A :class:`Transport` moves bytes and nothing else: it cuts what it receives into
frames (one :class:`~antireplay.mavlink.codec.FrameReader` per datagram, per TCP
client, per serial port) and hands them, with the peer they came from and the
count of garbage bytes skipped, to the router's ``deliver``.  It never decides
where to send: :meth:`Transport.send` writes to the peer the router names
(``None`` for the fixed destination of ``udpout``, ``tcp`` and serial).  Which
peers may receive is the router's: a peer is learned only from an authenticated
frame (:mod:`antireplay.mavlink.router`).  Every transport reads in its own
thread with a short timeout so that :meth:`Transport.close` returns promptly, and
bounds what a flood can cost: one frame of buffer per reader, ``max_clients``
TCP clients (more are closed at once and counted).
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import termios
import threading
import tty
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

from antireplay.mavlink.codec import FrameReader

#: A ``udpin`` sender's address or a ``tcpin`` client's connection number.
Peer = tuple[str, int] | int
#: ``deliver(transport, peer, frames, skipped_bytes)``: what a transport hands the router.
Deliver = Callable[["Transport", Peer | None, list[bytes], int], None]
DEFAULT_BAUD = 57_600
_POLL_S = 0.2  # read timeout: how soon a reader notices close()


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


class Transport:
    """Moves bytes for one endpoint (module docstring); subclasses per kind."""

    def __init__(self, spec: EndpointSpec, *, fixed: bool = True) -> None:
        self.spec = spec
        #: Whether the endpoint has a destination of its own (``send`` to peer ``None``).
        self.fixed = fixed
        self.errors: Counter[str] = Counter()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._deliver: Deliver | None = None

    @property
    def address(self) -> tuple[str, int]:
        """The local socket address (a port bound to 0 shows its number here)."""
        return self.spec.host, self.spec.port

    def start(self, deliver: Deliver) -> None:
        """Start reading; every frame goes to ``deliver``."""
        self._deliver = deliver
        self._spawn(self._run)

    def send(self, data: bytes, peer: Peer | None) -> bool:
        """Write ``data`` to ``peer``; False (and counted) if it could not be written."""
        try:
            self._write(data, peer)
        except OSError:
            self.errors["send"] += 1
            return False
        return True

    def _write(self, data: bytes, peer: Peer | None) -> None:
        """Write ``data`` to ``peer`` or raise OSError."""
        raise NotImplementedError

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=5)

    def _run(self) -> None:
        raise NotImplementedError

    def _spawn(self, target: Callable[[], None]) -> None:
        thread = threading.Thread(target=target, daemon=True, name=f"mavlink {self.spec.text}")
        self._threads.append(thread)
        thread.start()

    def _hand(self, peer: Peer | None, reader: FrameReader, data: bytes) -> None:
        frames = reader.feed(data)
        skipped, reader.skipped = reader.skipped, 0
        if (frames or skipped) and self._deliver is not None:
            self._deliver(self, peer, frames, skipped)


class UdpTransport(Transport):
    """``udpin`` (bound; answers peers the router names) or ``udpout`` (a fixed address)."""

    def __init__(self, spec: EndpointSpec) -> None:
        super().__init__(spec, fixed=spec.kind == "udpout")
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        if self.fixed:
            self.sock.connect((spec.host, spec.port))
        else:
            self.sock.bind((spec.host, spec.port))
        self.sock.settimeout(_POLL_S)

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.sock.getsockname()[:2]
        return str(host), int(port)

    def _write(self, data: bytes, peer: Peer | None) -> None:
        if isinstance(peer, tuple):
            self.sock.sendto(data, peer)
        else:
            self.sock.send(data)

    def close(self) -> None:
        super().close()
        self.sock.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                datagram, sender = self.sock.recvfrom(65_535)
            except TimeoutError:
                continue
            except (ConnectionRefusedError, ConnectionResetError):
                continue  # udpout: nobody listens there yet (ICMP port unreachable)
            except OSError:
                return
            reader = FrameReader()  # a datagram is judged alone: leftovers are garbage
            frames = reader.feed(datagram)
            skipped = reader.skipped + reader.pending
            if self._deliver is not None:
                self._deliver(self, None if self.fixed else sender, frames, skipped)


class TcpClientTransport(Transport):
    """``tcp:HOST:PORT``: connects, and reconnects after a loss (one peer: the server)."""

    def __init__(self, spec: EndpointSpec) -> None:
        super().__init__(spec)
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()

    def _write(self, data: bytes, peer: Peer | None) -> None:
        with self._lock:
            if self._sock is None:
                raise OSError("not connected")
            self._sock.sendall(data)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                sock = socket.create_connection((self.spec.host, self.spec.port), timeout=_POLL_S)
            except OSError:
                self.errors["connect"] += 1
                self._stop.wait(1.0)  # the autopilot or router is not up yet
                continue
            sock.settimeout(_POLL_S)
            with self._lock:
                self._sock = sock
            _read_stream(sock, self._stop, partial(self._hand, None, FrameReader()))
            with self._lock:
                self._sock = None
            sock.close()


class TcpServerTransport(Transport):
    """``tcpin:HOST:PORT``: each client is a peer (its connection number); at most
    ``max_clients`` at once, more are closed at once and counted."""

    def __init__(self, spec: EndpointSpec, max_clients: int = 16) -> None:
        super().__init__(spec, fixed=False)
        self.max_clients = max_clients
        self.server = socket.create_server((spec.host, spec.port))
        self.server.settimeout(_POLL_S)
        self._clients: dict[int, socket.socket] = {}
        self._next = 0
        self._lock = threading.Lock()

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.server.getsockname()[:2]
        return str(host), int(port)

    def _write(self, data: bytes, peer: Peer | None) -> None:
        client = self._clients.get(peer) if isinstance(peer, int) else None
        if client is None:
            raise OSError("client gone")
        client.sendall(data)

    def close(self) -> None:
        super().close()
        self.server.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self.server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with self._lock:
                if len(self._clients) >= self.max_clients:
                    self.errors["clients_refused"] += 1
                    client.close()
                    continue
                self._next += 1
                number = self._next
                self._clients[number] = client
            client.settimeout(_POLL_S)
            self._spawn(partial(self._serve, client, number))

    def _serve(self, client: socket.socket, number: int) -> None:
        _read_stream(client, self._stop, partial(self._hand, number, FrameReader()))
        with self._lock:
            self._clients.pop(number, None)
        client.close()


class SerialTransport(Transport):
    """A serial device (a flight controller's USB or telemetry port), raw at ``baud``."""

    def __init__(self, spec: EndpointSpec) -> None:
        super().__init__(spec)
        self.fd = os.open(spec.host, os.O_RDWR | os.O_NOCTTY)
        try:
            tty.setraw(self.fd)
            attrs = termios.tcgetattr(self.fd)
            speed = getattr(termios, f"B{spec.port}")
            attrs[4] = attrs[5] = speed  # ispeed, ospeed
            attrs[2] |= termios.CLOCAL | termios.CREAD
            termios.tcsetattr(self.fd, termios.TCSANOW, attrs)
        except (termios.error, OSError):
            os.close(self.fd)
            raise
        self._lock = threading.Lock()

    def _write(self, data: bytes, peer: Peer | None) -> None:
        view = memoryview(data)
        with self._lock:
            while view:
                view = view[os.write(self.fd, view) :]

    def close(self) -> None:
        super().close()
        with contextlib.suppress(OSError):
            os.close(self.fd)

    def _run(self) -> None:
        reader = FrameReader()
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self.fd], [], [], _POLL_S)
                if not ready:
                    continue
                data = os.read(self.fd, 4096)
            except OSError:
                self.errors["read"] += 1
                return  # the device went away (unplugged); the router counts nothing more
            if data:
                self._hand(None, reader, data)


def _read_stream(sock: socket.socket, stop: threading.Event, hand: Callable[[bytes], None]) -> None:
    """Read a TCP connection until it closes or ``stop`` is set."""
    while not stop.is_set():
        try:
            data = sock.recv(65_536)
        except TimeoutError:
            continue
        except OSError:
            return
        if not data:
            return
        hand(data)


def open_transport(spec: EndpointSpec) -> Transport:
    """The transport for ``spec`` (binds, connects or opens now: OSError if it cannot)."""
    if spec.kind in {"udpin", "udpout"}:
        return UdpTransport(spec)
    if spec.kind == "tcp":
        return TcpClientTransport(spec)
    if spec.kind == "tcpin":
        return TcpServerTransport(spec)
    return SerialTransport(spec)
