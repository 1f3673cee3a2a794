"""A seeded, lossy, bandwidth-limited radio between a PQ ground end and vehicle end, in
simulated time (a manual clock and an event queue): a retrying GCS on one side, a flight
controller that answers COMMAND_ACK on the other, each end pacing its air side as
``--air-bps`` makes the link do (:class:`~antireplay.mavlink.pq.link.Pacer`) when the
radio is slow.  Deterministic for a seed."""

from __future__ import annotations

import heapq
import itertools
import os
import random
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

from antireplay import ManualClock
from antireplay.core.errors import ReplayAttackError
from antireplay.mavlink.pq import GroundEnd, VehicleEnd
from antireplay.mavlink.pq.link import Pacer
from antireplay.mavlink.pq.wire import LINE_BITS

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as dialect


class _Keep:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


def build(make: Callable[[dialect.MAVLink], None], sysid: int) -> bytes:
    keep = _Keep()
    make(dialect.MAVLink(keep, srcSystem=sysid, srcComponent=190 if sysid == 255 else 1))
    return keep.frames[-1]


@dataclass
class Channel:
    """One direction of the radio: each frame lost with probability ``loss``; with ``bps``
    frames queue behind each other (a serial line, 10 bits a byte), then ``latency_s``."""

    rng: random.Random
    loss: float
    bps: int | None
    latency_s: float = 0.005
    busy_until: float = 0.0
    sent: int = 0

    def schedule(self, now: float, frame: bytes) -> float | None:
        """When ``frame`` arrives, or None: lost."""
        self.sent += len(frame)
        start = max(now, self.busy_until)
        self.busy_until = start + (LINE_BITS * len(frame) / self.bps if self.bps else 0.0)
        if self.rng.random() < self.loss:
            return None
        return self.busy_until + self.latency_s


@dataclass
class Radio:
    ground: GroundEnd
    vehicle: VehicleEnd
    clock: ManualClock
    loss: float
    bps: int | None = None
    seed: int = 1
    tick_s: float = 0.1
    events: list[tuple[float, int, Callable[[], None]]] = field(default_factory=list)
    delivered: Counter[float] = field(default_factory=Counter)  # param1 at the FC
    acks: list[float] = field(default_factory=list)  # times the GCS got an ACK
    refused: Counter[str] = field(default_factory=Counter)

    def __post_init__(self) -> None:
        rng = random.Random(self.seed)
        self.up = Channel(random.Random(rng.random()), self.loss, self.bps)
        self.down = Channel(random.Random(rng.random()), self.loss, self.bps)
        self._seq = itertools.count()
        self._acked = False
        self.fc = dialect.MAVLink(_Keep(), srcSystem=1, srcComponent=1)
        # each end's pacer (as ``--air-bps`` gives the link), when the radio is slow
        self.pacers = {} if self.bps is None else {
            id(channel): Pacer(self.bps, self.clock) for channel in (self.up, self.down)
        }  # fmt: skip

    def at(self, when: float, action: Callable[[], None]) -> None:
        heapq.heappush(self.events, (when, next(self._seq), action))

    def run_until(self, end: float) -> None:
        while self.events and self.events[0][0] <= end:
            when, _, action = heapq.heappop(self.events)
            self.clock.advance(max(0.0, when - self.clock.monotonic()))
            action()
        self.clock.advance(max(0.0, end - self.clock.monotonic()))

    def send(self, channel: Channel, frames: list[bytes], to: Callable[[bytes], None]) -> None:
        pacer = self.pacers.get(id(channel))
        if pacer is None:
            self._transmit(channel, frames, to)
            return
        pacer.push(frames, None)
        self._pump(channel, pacer, to)

    def _pump(self, channel: Channel, pacer: Pacer, to: Callable[[bytes], None]) -> None:
        ready, wait_s = pacer.pop()
        self._transmit(channel, [frame for frame, _ in ready], to)
        if pacer.urgent or pacer.bulk:
            self.at(self.clock.monotonic() + wait_s, lambda: self._pump(channel, pacer, to))

    def _transmit(self, channel: Channel, frames: list[bytes], to: Callable[[bytes], None]) -> None:
        for frame in frames:
            arrive = channel.schedule(self.clock.monotonic(), frame)
            if arrive is not None:
                self.at(arrive, lambda f=frame: to(f))  # type: ignore[misc]

    def to_vehicle(self, raw: bytes) -> None:
        try:
            out = self.vehicle.from_air(raw)
        except ReplayAttackError as exc:
            self.refused[f"vehicle:{exc.code}"] += 1
            return
        self.send(self.down, out.air, self.to_ground)
        for plain in out.local:  # the flight controller: every command answered at once
            msg = dialect.MAVLink(_Keep()).decode(bytearray(plain))
            if msg.get_type() == "COMMAND_LONG":
                self.delivered[msg.param1] += 1
                ack = self.ack(msg.command)
                self.send(self.down, self.vehicle.from_local(ack), self.to_ground)

    def ack(self, command: int) -> bytes:
        """The flight controller's COMMAND_ACK (its sequence number counting, as on a real one)."""
        keep = _Keep()
        self.fc.file = keep
        self.fc.command_ack_send(command, 0, 0, 0, 255, 190)
        return keep.frames[-1]

    def to_ground(self, raw: bytes) -> None:
        try:
            out = self.ground.from_air(raw)
        except ReplayAttackError as exc:
            self.refused[f"ground:{exc.code}"] += 1
            return
        self.send(self.up, out.air, self.to_vehicle)
        self.to_gcs(out.local)

    def to_gcs(self, frames: list[bytes]) -> None:
        for plain in frames:
            if dialect.MAVLink(_Keep()).decode(bytearray(plain)).get_type() == "COMMAND_ACK":
                self._acked = True

    def ticking(self) -> None:
        self.send(self.up, self.ground.tick(), self.to_vehicle)
        self.send(self.down, self.vehicle.tick(), self.to_ground)
        self.at(self.clock.monotonic() + self.tick_s, self.ticking)

    def heartbeat(self) -> None:
        """Both sides' heartbeats, once a second (the ground station's cross its commands)."""
        beat = build(lambda m: m.heartbeat_send(2, 3, 0, 0, 4), 1)
        self.send(self.down, self.vehicle.from_local(beat), self.to_ground)
        if self.ground.session is not None:
            gcs = build(lambda m: m.heartbeat_send(6, 8, 0, 0, 4), 255)
            self.send(self.up, self.ground.from_local(gcs), self.to_vehicle)
        self.at(self.clock.monotonic() + 1.0, self.heartbeat)

    def start(self, within_s: float = 30.0) -> float:
        """Hand-shake; the time the ground end's session came up (or inf after
        ``within_s``)."""
        began = self.clock.monotonic()
        self.send(self.up, self.ground.handshake(), self.to_vehicle)
        self.at(began + self.tick_s, self.ticking)
        self.at(began + 1.0, self.heartbeat)
        while self.ground.session is None and self.clock.monotonic() < began + within_s:
            self.run_until(self.clock.monotonic() + 0.05)
        return self.clock.monotonic() - began if self.ground.session else float("inf")

    def command(self, param1: float, tries: int = 4, every_s: float = 1.5) -> float | None:
        """One COMMAND_LONG from a GCS that tries ``tries`` times ``every_s`` apart: the
        time to its ACK, or None."""
        self._acked, began = False, self.clock.monotonic()
        arm = build(lambda m: m.command_long_send(1, 1, 400, 0, param1, 0, 0, 0, 0, 0, 0), 255)
        for attempt in range(tries):
            out = self.ground.handle_local(arm)
            self.to_gcs(out.local)
            self.send(self.up, out.air, self.to_vehicle)
            deadline = began + (attempt + 1) * every_s
            while not self._acked and self.clock.monotonic() < deadline:
                self.run_until(min(deadline, self.clock.monotonic() + 0.01))
            if self._acked:
                return self.clock.monotonic() - began
        return None
