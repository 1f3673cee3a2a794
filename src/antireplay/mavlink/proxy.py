"""MAVLink v2 UDP proxy: forwards only the frames each direction's guard accepts.

Theory of operation
-------------------
:class:`MavlinkProxy` sits between a ground station and a vehicle: frames from the
ground side go to the vehicle only if ``inbound`` (a
:class:`~antireplay.mavlink.guard.MavlinkGuard`) accepts them; frames from the
vehicle go back to the ground peer only if ``outbound`` accepts them.  A datagram
is cut into frames (:func:`~antireplay.mavlink.codec.split_frames`) and each frame
judged alone: the accepted ones are forwarded together, each refusal is counted
(:class:`ProxyStats`) and handed to ``on_reject``.

The ground peer (where telemetry goes) is learned only from a datagram in which at
least one *signed* frame was accepted: garbage, forged or replayed frames, and
unsigned allow-listed frames (anyone can make those), never move it, so one spoofed
datagram cannot redirect the vehicle's telemetry.  Until a peer has authenticated,
telemetry is dropped and counted as ``outbound:NO_PEER``.  Residual: an attacker who
sees a ground frame before the proxy does can race it in from its own address; that
frame is authentic and fresh, so the peer follows it (UDP carries no authenticated
address; the same holds for every MAVLink endpoint).  Each side's authenticated
source systems are refused on the other side (the guard's ``refused_sources``; see
*Direction binding* in :mod:`antireplay.mavlink.guard`).

:meth:`MavlinkProxy.start` starts both guards (lease, flusher) before forwarding;
:meth:`MavlinkProxy.stop` stops forwarding, then flushes both and releases their
leases.
"""

from __future__ import annotations

import socket
import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from antireplay.errors import ReplayAttackError
from antireplay.mavlink.codec import split_frames
from antireplay.mavlink.guard import MavlinkGuard


@dataclass
class ProxyStats:
    """What the proxy did, per direction."""

    forwarded: Counter[str] = field(default_factory=Counter)
    dropped: Counter[str] = field(default_factory=Counter)


class MavlinkProxy:
    """UDP proxy between a ground station and a vehicle, one guard per direction (module
    docstring).  ``on_reject`` receives each rejection (for audit and metrics)."""

    def __init__(
        self,
        listen: tuple[str, int],
        forward: tuple[str, int],
        inbound: MavlinkGuard,
        outbound: MavlinkGuard,
        on_reject: Callable[[str, ReplayAttackError, bytes], Any] | None = None,
    ) -> None:
        self.ground = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.ground.bind(listen)
        self.vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.vehicle.connect(forward)
        for sock in (self.ground, self.vehicle):
            sock.settimeout(0.2)  # lets the loops notice stop() promptly
        self.inbound, self.outbound = inbound, outbound
        self.on_reject = on_reject
        self.stats = ProxyStats()
        self._peer: tuple[str, int] | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.ground.getsockname()[:2]
        return str(host), int(port)

    @property
    def peer(self) -> tuple[str, int] | None:
        """Where telemetry goes: the last ground address that sent an authenticated frame."""
        return self._peer

    def start(self) -> None:
        """Start both guards (lease, flusher), then the two forwarding loops."""
        self.inbound.start()
        self.outbound.start()
        for target in (self._from_ground, self._from_vehicle):
            thread = threading.Thread(target=target, daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        """Stop forwarding, then flush both guards and release their leases."""
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=5)
        for sock in (self.ground, self.vehicle):
            sock.close()
        self.inbound.stop()
        self.outbound.stop()

    def _filter(
        self, direction: str, guard: MavlinkGuard, other: MavlinkGuard, datagram: bytes
    ) -> tuple[bytes, bool]:
        """The accepted frames, and whether any of them was signed (authenticated)."""
        out, authenticated = bytearray(), False
        try:
            frames = split_frames(datagram)
        except ReplayAttackError as exc:
            self._reject(direction, exc, datagram)
            return b"", False
        for raw in frames:
            try:
                verdict = guard.open(raw)
            except ReplayAttackError as exc:
                self._reject(direction, exc, raw)
                continue
            if verdict.signed:
                authenticated = True
                other.refused_sources.add(verdict.stream[0])  # this side's system, from now on
            self.stats.forwarded[direction] += 1
            out += raw
        return bytes(out), authenticated

    def _reject(self, direction: str, exc: ReplayAttackError, raw: bytes) -> None:
        self.stats.dropped[f"{direction}:{exc.code}"] += 1
        if self.on_reject is not None:
            self.on_reject(direction, exc, raw)

    def _from_ground(self) -> None:
        while not self._stop.is_set():
            try:
                datagram, peer = self.ground.recvfrom(65_535)
            except TimeoutError:
                continue
            except OSError:
                return
            allowed, authenticated = self._filter("inbound", self.inbound, self.outbound, datagram)
            if authenticated:
                self._peer = peer
            if allowed:
                try:
                    self.vehicle.send(allowed)
                except OSError:
                    self.stats.dropped["inbound:VEHICLE_UNREACHABLE"] += 1

    def _from_vehicle(self) -> None:
        while not self._stop.is_set():
            try:
                datagram = self.vehicle.recv(65_535)
            except TimeoutError:
                continue
            except (ConnectionRefusedError, ConnectionResetError):
                continue  # the vehicle is not up yet: ICMP port unreachable
            except OSError:
                return
            allowed, _ = self._filter("outbound", self.outbound, self.inbound, datagram)
            if not allowed:
                continue
            peer = self._peer
            if peer is None:
                self.stats.dropped["outbound:NO_PEER"] += 1
                continue
            try:
                self.ground.sendto(allowed, peer)
            except OSError:
                self.stats.dropped["outbound:GROUND_UNREACHABLE"] += 1
