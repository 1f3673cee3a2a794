"""A telemetry radio on loopback: a lossy, optionally slow UDP relay for MAVLink over UDP.

Two sockets: the **ground** socket, bound to :attr:`Radio.port`, where the ground side
sends (its address is learned from what it sends, as a radio's serial port has one peer),
and the **air** socket, which sends to the fixed ``remote`` address (the vehicle side) and
takes its answers.  Each datagram is one MAVLink frame as the link wrote it.

Per direction (``uplink`` ground to vehicle, ``downlink`` back), every datagram is lost
independently with probability ``loss``, decided by that direction's own RNG seeded from
``seed`` (the same seed and the same traffic lose the same datagrams).  With ``bps`` set,
a direction is a serial line: a datagram takes ``len * 10 / bps`` seconds of airtime
(start and stop bits, as a UART at 57,600 baud moves 5,760 bytes a second), one after
another; it waits in a queue of ``queue_bytes`` (a SiK radio buffers 2,048 bytes from its
serial port) and is dropped on arrival if the queue cannot hold it (``overflowed``).  A
datagram keeps its place in the queue until its airtime has passed; it is lost (or not)
when it leaves.  Without ``bps`` datagrams are forwarded as they come.

:class:`AirCounts` per direction: datagrams and bytes received, put on air (airtime used,
lost ones included), delivered, lost and overflowed; ``on_air`` sees every datagram put
on air (a benchmark may classify them).  Threads: one receiver per direction, and one
transmitter per direction when ``bps`` is set; :meth:`Radio.stop` joins them all.

Run as a process: ``python -m harness.radio --remote HOST:PORT [--port P] [--loss
0.05] [--bps 57600] [--queue-bytes 2048] [--seed 1]`` prints ``radio PORT`` once it
listens and, at SIGTERM or SIGINT, the counts as one JSON line.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import random
import signal
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from types import FrameType, TracebackType

#: A UART's start and stop bits: 10 bits on the line per byte.
BITS_PER_BYTE = 10
#: A SiK radio's serial receive buffer (bytes waiting for the air).
SIK_QUEUE_BYTES = 2_048
#: The usual telemetry radio baud rate.
SIK_BAUD = 57_600
DIRECTIONS = ("uplink", "downlink")

Address = tuple[str, int]
OnAir = Callable[[str, bytes], None]


@dataclass
class AirCounts:
    """One direction's traffic; ``on_air_bytes`` is the airtime used, lost datagrams too."""

    received: int = 0
    received_bytes: int = 0
    on_air: int = 0
    on_air_bytes: int = 0
    delivered: int = 0
    delivered_bytes: int = 0
    lost: int = 0
    overflowed: int = 0
    first_at: float | None = None  # time.monotonic() of the first datagram received


def airtime(size: int, bps: int) -> float:
    """Seconds a datagram of ``size`` bytes takes on a serial line at ``bps`` baud."""
    return size * BITS_PER_BYTE / bps


class _Direction:
    """One way through the radio: its RNG, its queue, its counts."""

    def __init__(self, name: str, radio: Radio, out: socket.socket) -> None:
        self.name = name
        self.radio = radio
        self.out = out
        self.rng = random.Random(f"{radio.seed}/{name}")
        self.counts = AirCounts()
        self.queue: deque[tuple[bytes, Address]] = deque()
        self.queued_bytes = 0
        self.ready = threading.Condition(radio.lock)

    def arrive(self, data: bytes, to: Address) -> None:
        """Take a datagram from the socket: forward it now, or queue it for its airtime."""
        with self.radio.lock:
            if self.counts.first_at is None:
                self.counts.first_at = time.monotonic()
            self.counts.received += 1
            self.counts.received_bytes += len(data)
            if self.radio.bps is not None:
                if self.queued_bytes + len(data) > self.radio.queue_bytes:
                    self.counts.overflowed += 1
                else:
                    self.queue.append((data, to))
                    self.queued_bytes += len(data)
                    self.ready.notify()
                return
        self.transmit(data, to)

    def transmit(self, data: bytes, to: Address) -> None:
        """Put a datagram on air: it uses its airtime whether or not it is lost."""
        with self.radio.lock:
            self.counts.on_air += 1
            self.counts.on_air_bytes += len(data)
            lost = self.rng.random() < self.radio.loss
            if lost:
                self.counts.lost += 1
            else:
                self.counts.delivered += 1
                self.counts.delivered_bytes += len(data)
        if self.radio.on_air is not None:
            self.radio.on_air(self.name, data)
        if not lost:
            with contextlib.suppress(OSError):  # nobody listens there (yet): not our care
                self.out.sendto(data, to)

    def serialise(self) -> None:
        """The transmitter: one datagram at a time, each for its airtime."""
        bps = self.radio.bps
        assert bps is not None
        free_at = time.monotonic()
        while True:
            with self.radio.lock:
                while not self.queue and not self.radio.stopping.is_set():
                    self.ready.wait()
                if self.radio.stopping.is_set():
                    return
                data, to = self.queue[0]
            free_at = max(free_at, time.monotonic()) + airtime(len(data), bps)
            if self.radio.stopping.wait(max(0.0, free_at - time.monotonic())):
                return
            with self.radio.lock:
                self.queue.popleft()
                self.queued_bytes -= len(data)
            self.transmit(data, to)


class Radio:
    """A lossy, optionally bandwidth-limited relay between a ground side and ``remote``."""

    def __init__(
        self,
        remote: Address,
        *,
        loss: float = 0.0,
        bps: int | None = None,
        queue_bytes: int = SIK_QUEUE_BYTES,
        seed: int = 0,
        port: int = 0,
        host: str = "127.0.0.1",
        on_air: OnAir | None = None,
    ) -> None:
        if not 0.0 <= loss <= 1.0:
            raise ValueError(f"loss {loss} is not a probability")
        if bps is not None and bps <= 0:
            raise ValueError(f"bps {bps} must be positive (None: unlimited)")
        self.remote, self.loss, self.bps = remote, loss, bps
        self.queue_bytes, self.seed, self.on_air = queue_bytes, seed, on_air
        self.lock = threading.Lock()
        self.stopping = threading.Event()
        self.ground_sock = self._socket((host, port))
        self.air_sock = self._socket((host, 0))
        self.port = int(self.ground_sock.getsockname()[1])
        self.ground_peer: Address | None = None
        self.uplink = _Direction("uplink", self, self.air_sock)
        self.downlink = _Direction("downlink", self, self.ground_sock)
        self._threads = [
            threading.Thread(target=self._receive_ground, name="radio-uplink", daemon=True),
            threading.Thread(target=self._receive_air, name="radio-downlink", daemon=True),
        ]
        if bps is not None:
            self._threads += [
                threading.Thread(target=d.serialise, name=f"radio-{d.name}-air", daemon=True)
                for d in (self.uplink, self.downlink)
            ]

    @staticmethod
    def _socket(address: Address) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        sock.bind(address)
        sock.settimeout(0.1)
        return sock

    def start(self) -> Radio:
        for thread in self._threads:
            thread.start()
        return self

    def _receive_ground(self) -> None:
        while not self.stopping.is_set():
            try:
                data, peer = self.ground_sock.recvfrom(65_536)
            except (TimeoutError, OSError):
                continue
            self.ground_peer = peer
            self.uplink.arrive(data, self.remote)

    def _receive_air(self) -> None:
        while not self.stopping.is_set():
            try:
                data, _ = self.air_sock.recvfrom(65_536)
            except (TimeoutError, OSError):
                continue
            if self.ground_peer is not None:  # nobody on the ground yet: nowhere to go
                self.downlink.arrive(data, self.ground_peer)

    def counts(self) -> dict[str, AirCounts]:
        """A copy of both directions' counts, taken together."""
        with self.lock:
            return {d.name: AirCounts(**asdict(d.counts)) for d in (self.uplink, self.downlink)}

    def on_air_bytes(self) -> int:
        """Bytes put on air so far, both directions (the airtime used, lost datagrams too)."""
        return sum(c.on_air_bytes for c in self.counts().values())

    def stop(self) -> None:
        self.stopping.set()
        with self.lock:
            for direction in (self.uplink, self.downlink):
                direction.ready.notify_all()
        for thread in self._threads:
            if thread.is_alive():
                thread.join()
        self.ground_sock.close()
        self.air_sock.close()

    def __enter__(self) -> Radio:
        return self.start()

    def __exit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()


def _address(text: str) -> Address:
    host, _, port = text.rpartition(":")
    return host or "127.0.0.1", int(port)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m harness.radio", description=__doc__)
    parser.add_argument("--remote", type=_address, required=True, help="the vehicle side")
    parser.add_argument("--port", type=int, default=0, help="the ground side's port (0: any)")
    parser.add_argument("--loss", type=float, default=0.0, help="loss probability per datagram")
    parser.add_argument("--bps", type=int, default=None, help="serial baud rate (none: unlimited)")
    parser.add_argument("--queue-bytes", type=int, default=SIK_QUEUE_BYTES)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    done = threading.Event()

    def stop(signum: int, frame: FrameType | None) -> None:
        done.set()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    radio = Radio(
        args.remote, loss=args.loss, bps=args.bps, queue_bytes=args.queue_bytes,
        seed=args.seed, port=args.port,
    ).start()  # fmt: skip
    print(f"radio {radio.port}", flush=True)
    done.wait()
    radio.stop()
    print(json.dumps({name: asdict(c) for name, c in radio.counts().items()}), flush=True)


if __name__ == "__main__":
    main()
