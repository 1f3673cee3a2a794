"""MAVLink endpoints: the transports behind the connection strings MAVLink users type.

Theory of operation
-------------------
The strings (:func:`parse_endpoint`, :func:`is_local`) are :mod:`.endpoint_spec`'s.  A
:class:`Transport` moves bytes and nothing else: it cuts what it receives into frames,
parsed once (:class:`~antireplay.mavlink.codec.Frame`), and hands them with their peer and
the garbage bytes dropped to the router's ``deliver``.  A stream (TCP, serial) resyncs
past garbage (:class:`~antireplay.mavlink.codec.FrameReader`) as flight stacks do; a UDP
datagram is whole frames or nothing, dropped whole, so an authentic frame wrapped in
garbage never passes.  :meth:`Transport.send` writes to the peer the router names
(``None``: the fixed destination of ``udpout``, ``tcp``, serial); which peers may receive
is the router's (learned from authenticated frames).  Each transport reads in its own
thread with a short timeout (prompt :meth:`Transport.close`) and bounds a flood: one frame
of buffer per reader, ``max_clients`` TCP clients.

**Never blocked by a network peer**: writes are non-blocking, and a TCP peer that cannot
take a whole frame now is hung up on (``stalled``).  **A full ``tcpin`` makes room**: a new
client takes the slot of the longest-connected one that never authenticated
(:meth:`Transport.authenticated`; ``clients_evicted``), else is refused
(``clients_refused``).  **A serial device that goes away** reads as end of file (``eof``)
and is reopened with a backoff of ``REOPEN_S`` doubling to ``REOPEN_MAX_S`` (``reopen``).
Every such event is counted in :attr:`Transport.errors` per kind
(``antireplay_mavlink_transport_errors_total``) and logged, at most once per
``LOG_EVERY_S`` per kind after the first.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import select
import socket
import termios
import threading
import time
import tty
from collections import Counter
from collections.abc import Callable
from functools import partial

from antireplay.core.errors import InvalidFrameError
from antireplay.mavlink.codec import Frame, FrameReader, split_parsed
from antireplay.mavlink.endpoint_spec import (
    DEFAULT_BAUD,
    EndpointSpec,
    addresses,
    is_local,
    parse_endpoint,
)

#: A ``udpin`` sender's address or a ``tcpin`` client's connection number.
Peer = tuple[str, int] | int
#: ``deliver(transport, peer, frames, dropped_bytes)``: what a transport hands the router.
Deliver = Callable[["Transport", Peer | None, list[Frame], int], None]
REOPEN_S, REOPEN_MAX_S = 0.05, 2.0  # a serial device's reopen backoff: first, longest
LOG_EVERY_S = 60.0  # one log line per endpoint and error kind at most this often
_POLL_S = 0.2  # read timeout: how soon a reader notices close()
log = logging.getLogger("antireplay.mavlink")
__all__ = [  # the connection strings' names stay importable from here
    "DEFAULT_BAUD", "LOG_EVERY_S", "REOPEN_MAX_S", "REOPEN_S", "Deliver", "EndpointSpec", "Peer",
    "SerialTransport", "TcpClientTransport", "TcpServerTransport", "Transport", "UdpTransport",
    "addresses", "is_local", "open_transport", "parse_endpoint",
]  # fmt: skip


class Transport:
    """Moves bytes for one endpoint (module docstring); subclasses per kind."""

    def __init__(self, spec: EndpointSpec, *, fixed: bool = True) -> None:
        self.spec = spec
        #: Whether the endpoint has a destination of its own (``send`` to peer ``None``).
        self.fixed = fixed
        #: Transport errors per kind (module docstring), for metrics.
        self.errors: Counter[str] = Counter()
        self._logged: dict[str, tuple[float, int]] = {}  # kind: (when logged, count then)
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
        """Write ``data`` to ``peer`` without waiting; False (and counted) if it was not."""
        try:
            self._write(data, peer)
        except _StalledError:  # counted, and the peer hung up on
            return False
        except OSError as exc:  # not connected: a client gone, a device or server down
            self._error("not_connected" if exc.errno == errno.ENOTCONN else "send", exc)
            return False
        return True

    def authenticated(self, peer: Peer) -> None:
        """The router accepted a frame from ``peer`` (a ``tcpin`` client keeps its slot)."""

    def _write(self, data: bytes, peer: Peer | None) -> None:
        """Write ``data`` to ``peer`` or raise OSError."""
        raise NotImplementedError

    def close(self) -> None:
        self._stop.set()
        for thread in list(self._threads):
            thread.join(timeout=5)

    def _run(self) -> None:
        raise NotImplementedError

    def _spawn(self, target: Callable[[], None]) -> None:
        thread = threading.Thread(target=target, daemon=True, name=f"mavlink {self.spec.text}")
        self._threads = [*(t for t in self._threads if t.is_alive()), thread]
        thread.start()

    def _hand(self, peer: Peer | None, reader: FrameReader, data: bytes) -> None:
        frames = reader.feed_parsed(data)
        skipped, reader.skipped = reader.skipped, 0
        if (frames or skipped) and self._deliver is not None:
            self._deliver(self, peer, frames, skipped)

    def _error(self, kind: str, detail: object, level: int = logging.WARNING) -> None:
        """Count an error of ``kind``; log the first at once, then one line per
        ``LOG_EVERY_S`` saying how many came since."""
        self.errors[kind] += 1
        now = time.monotonic()
        last = self._logged.get(kind)
        if last is not None and now - last[0] < LOG_EVERY_S:
            return
        since = self.errors[kind] - (last[1] if last else 0) - 1
        more = f" ({since} more since the last line)" if since else ""
        self._logged[kind] = (now, self.errors[kind])
        log.log(level, "%s: %s: %s%s", self.spec.text, kind, detail, more)


class UdpTransport(Transport):
    """``udpin`` (bound; answers peers the router names) or ``udpout`` (a fixed address)."""

    def __init__(self, spec: EndpointSpec) -> None:
        super().__init__(spec, fixed=spec.kind == "udpout")
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if self.fixed:
                self.sock.connect((spec.host, spec.port))
            else:
                self.sock.bind((spec.host, spec.port))
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)  # read until empty, then wait (module docstring)

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.sock.getsockname()[:2]
        return str(host), int(port)

    def _write(self, data: bytes, peer: Peer | None) -> None:
        if isinstance(peer, tuple):
            self.sock.sendto(data, socket.MSG_DONTWAIT, peer)
        else:
            self.sock.send(data, socket.MSG_DONTWAIT)

    def close(self) -> None:
        super().close()
        self.sock.close()

    def _run(self) -> None:
        recvfrom, fixed = self.sock.recvfrom, self.fixed
        poller = select.poll()
        poller.register(self.sock, select.POLLIN)
        while not self._stop.is_set():
            try:
                datagram, sender = recvfrom(65_535)
            except BlockingIOError:  # drained: wait for the next (or for close())
                poller.poll(_POLL_S * 1000)
                continue
            except (ConnectionRefusedError, ConnectionResetError):
                continue  # udpout: nobody listens there yet (ICMP port unreachable)
            except OSError as exc:
                if not self._stop.is_set():
                    self._error("read", exc)
                    self._stop.wait(_POLL_S)
                continue
            try:
                frames, dropped = split_parsed(datagram), 0
            except InvalidFrameError:  # garbage around a frame, a frame cut short
                frames, dropped = [], len(datagram)
            if self._deliver is not None:
                self._deliver(self, None if fixed else sender, frames, dropped)


class _StalledError(OSError):
    """A peer that could not take a whole frame now: counted as ``stalled``, hung up on."""


def _send_whole(sock: socket.socket, data: bytes) -> None:
    """Send all of ``data`` now; BlockingIOError if the socket took less (the caller
    hangs up: the stream ends with part of this frame, never spliced into the next)."""
    sent = sock.send(data, socket.MSG_DONTWAIT)
    if sent != len(data):
        raise BlockingIOError(errno.EAGAIN, f"took {sent} of {len(data)} bytes")


def _hang_up(sock: socket.socket) -> None:
    """End a connection another thread reads: its ``recv`` sees the end and closes it."""
    with contextlib.suppress(OSError):
        sock.shutdown(socket.SHUT_RDWR)


class TcpClientTransport(Transport):
    """``tcp:HOST:PORT``: connects, and reconnects after a loss (one peer: the server)."""

    def __init__(self, spec: EndpointSpec) -> None:
        super().__init__(spec)
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()

    def _write(self, data: bytes, peer: Peer | None) -> None:
        with self._lock:
            if self._sock is None:
                raise OSError(errno.ENOTCONN, "not connected")
            try:
                _send_whole(self._sock, data)
            except BlockingIOError as exc:
                self._error("stalled", f"disconnected: it does not read ({exc.strerror})")
                _hang_up(self._sock)
                self._sock = None
                raise _StalledError from exc

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                sock = socket.create_connection((self.spec.host, self.spec.port), timeout=_POLL_S)
            except OSError as exc:
                self._error("connect", exc)
                self._stop.wait(1.0)  # the autopilot or router is not up yet
                continue
            sock.setblocking(False)
            with self._lock:
                self._sock = sock
            _read_stream(sock, self._stop, partial(self._hand, None, FrameReader()))
            with self._lock:
                self._sock = None
            sock.close()
            if not self._stop.is_set():
                self._error("eof", "connection lost; reconnecting")


class TcpServerTransport(Transport):
    """``tcpin:HOST:PORT``: each client is a peer (its connection number); at most
    ``max_clients`` at once (module docstring: a full server makes room)."""

    def __init__(self, spec: EndpointSpec, max_clients: int = 16) -> None:
        super().__init__(spec, fixed=False)
        self.max_clients = max_clients
        self.server = socket.create_server((spec.host, spec.port))
        self.server.settimeout(_POLL_S)
        self._clients: dict[int, socket.socket] = {}  # in connection order
        self._trusted: set[int] = set()  # clients that sent a frame the router accepted
        self._next = 0
        self._lock = threading.Lock()

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.server.getsockname()[:2]
        return str(host), int(port)

    def authenticated(self, peer: Peer) -> None:
        if isinstance(peer, int):
            with self._lock:
                if peer in self._clients:
                    self._trusted.add(peer)

    def _write(self, data: bytes, peer: Peer | None) -> None:
        with self._lock:  # never held long: the send does not wait
            client = self._clients.get(peer) if isinstance(peer, int) else None
            if client is None or not isinstance(peer, int):
                raise OSError(errno.ENOTCONN, "client gone")
            try:
                _send_whole(client, data)
            except BlockingIOError as exc:
                self._error("stalled", f"client {peer} disconnected: it does not read ({exc})")
                del self._clients[peer]
                self._trusted.discard(peer)
                _hang_up(client)
                raise _StalledError from exc

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
                if len(self._clients) >= self.max_clients and not self._make_room():
                    self._error("clients_refused", f"{self.max_clients} clients, all authenticated")
                    client.close()
                    continue
                client.setblocking(False)
                self._next += 1
                number = self._next
                self._clients[number] = client
            self._spawn(partial(self._serve, client, number))

    def _make_room(self) -> bool:
        """Disconnect the oldest client that never authenticated (caller holds ``_lock``)."""
        idle = next((n for n in self._clients if n not in self._trusted), None)
        if idle is None:
            return False
        self._error("clients_evicted", f"client {idle} never authenticated: gave its slot")
        _hang_up(self._clients.pop(idle))
        return True

    def _serve(self, client: socket.socket, number: int) -> None:
        _read_stream(client, self._stop, partial(self._hand, number, FrameReader()))
        with self._lock:
            if self._clients.get(number) is client:
                del self._clients[number]
            self._trusted.discard(number)
        client.close()


class SerialTransport(Transport):
    """A serial device (a flight controller's USB or telemetry port), raw at ``baud``;
    opened again when it comes back after going away (module docstring)."""

    def __init__(self, spec: EndpointSpec) -> None:
        super().__init__(spec)
        self.fd: int | None = self._open()
        self._lock = threading.Lock()

    def _open(self) -> int:
        """Open and configure the device; OSError (naming it) if it cannot be."""
        fd = os.open(self.spec.host, os.O_RDWR | os.O_NOCTTY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # one process per device
        except BlockingIOError:
            os.close(fd)
            raise OSError(errno.EBUSY, "held by another process", self.spec.host) from None
        try:
            tty.setraw(fd)
            attrs = termios.tcgetattr(fd)
            speed = getattr(termios, f"B{self.spec.port}")
            attrs[4] = attrs[5] = speed  # ispeed, ospeed
            attrs[2] |= termios.CLOCAL | termios.CREAD
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
        except termios.error as exc:
            os.close(fd)
            code, reason = exc.args
            raise OSError(code, f"not a serial port ({reason})", self.spec.host) from None
        except OSError:
            os.close(fd)
            raise
        return fd

    def _write(self, data: bytes, peer: Peer | None) -> None:
        view = memoryview(data)
        with self._lock:
            if self.fd is None:
                raise OSError(errno.ENOTCONN, "device gone; reopening")
            while view:
                view = view[os.write(self.fd, view) :]

    def close(self) -> None:
        super().close()
        with self._lock:
            fd, self.fd = self.fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)

    def _run(self) -> None:
        delay = REOPEN_S
        while not self._stop.is_set():
            fd = self.fd
            if fd is None:
                return
            if self._read(fd):
                delay = REOPEN_S  # it worked for a while: the next outage starts afresh
            with self._lock:
                self.fd = None
            with contextlib.suppress(OSError):
                os.close(fd)
            delay = self._reopen(delay)

    def _read(self, fd: int) -> bool:
        """Read until the device goes away (counted as ``eof`` or ``read``) or ``close()``;
        True if anything was read."""
        reader, got = FrameReader(), False
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([fd], [], [], _POLL_S)
                data = os.read(fd, 4096) if ready else None
            except OSError as exc:
                gone = exc.errno in {errno.EIO, errno.ENXIO, errno.ENODEV}
                self._error("eof" if gone else "read", f"{exc}; reopening")
                break
            if data == b"":  # the other side of a pty closed; a USB device unplugged
                self._error("eof", "the device went away; reopening")
                break
            if data:
                got = True
                self._hand(None, reader, data)
        if reader.pending and self._deliver is not None:  # a frame cut short: garbage
            self._deliver(self, None, [], reader.pending)
        return got

    def _reopen(self, delay: float) -> float:
        """Open the device again after ``delay``, doubling to ``REOPEN_MAX_S`` between
        attempts; the delay to wait after the next loss."""
        while not self._stop.wait(delay):
            delay = min(2 * delay, REOPEN_MAX_S)
            try:
                fd = self._open()
            except OSError as exc:
                self._error("reopen", exc)
                continue
            with self._lock:
                self.fd = fd
            log.info("%s: opened again", self.spec.text)
            break
        return delay


def _read_stream(sock: socket.socket, stop: threading.Event, hand: Callable[[bytes], None]) -> None:
    """Read a non-blocking TCP connection until it closes or ``stop`` is set (non-blocking,
    so that a send from another thread never waits either)."""
    poller = select.poll()
    poller.register(sock, select.POLLIN)
    while not stop.is_set():
        if not poller.poll(_POLL_S * 1000):
            continue
        try:
            data = sock.recv(65_536)
        except BlockingIOError:
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
