"""Both ends of a PQ link in one process, the air between them a list a test can reorder,
drop or tamper with; the keys and the frames (pymavlink-built) the PQ end tests share."""

from __future__ import annotations

import os
import struct
from collections.abc import Callable
from typing import Any

from cryptography.hazmat.primitives.asymmetric import mldsa, mlkem

from antireplay import ManualClock
from antireplay.core.errors import ReplayAttackError
from antireplay.mavlink.codec import parse_frame
from antireplay.mavlink.pq import DIALECT, MSG_CHUNK, GroundEnd, VehicleEnd, pack_v2, parse_chunk
from antireplay.pq.session import Initiator, Responder

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as dialect

GCS_KEY = mldsa.MLDSA87PrivateKey.generate()
STRANGER_KEY = mldsa.MLDSA87PrivateKey.generate()  # a key the vehicle end does not know
ROBOT_KEM = mlkem.MLKEM1024PrivateKey.generate()
ARM = 400


class Keep:
    """pymavlink's output file, kept in a list."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


def plain(build: Callable[[dialect.MAVLink], None], sysid: int = 255) -> bytes:
    """One unsigned MAVLink v2 frame built by pymavlink."""
    keep = Keep()
    mav = dialect.MAVLink(keep, srcSystem=sysid, srcComponent=190)
    build(mav)
    return keep.frames[-1]


def raw_chunk(fields: tuple[int, ...], data: bytes, sysid: int = 255, compid: int = 197) -> bytes:
    """A PQ_CHUNK frame with any header fields (what an attacker can send)."""
    payload = struct.pack("<HBBBB", *fields) + data
    return pack_v2(MSG_CHUNK, payload, DIALECT[MSG_CHUNK][0], sysid=sysid, compid=compid, seq=0)


def arm(target: int = 1, param1: float = 1.0) -> bytes:
    return plain(lambda m: m.command_long_send(target, 1, ARM, 0, param1, 0, 0, 0, 0, 0, 0))


class EndPair:
    """Both ends, the air between them a list the test can reorder, drop or tamper with."""

    def __init__(self, clock: ManualClock, max_sessions: int = 4, **ground: Any) -> None:
        self.clock = clock
        self.responder = Responder(
            ROBOT_KEM, {"gcs": GCS_KEY.public_key()}, clock=clock, max_sessions=max_sessions
        )
        self.ground = self.new_ground(**ground)
        self.vehicle = VehicleEnd(self.responder, clock=clock)
        self.delivered: list[bytes] = []  # plain frames at the flight controller
        self.telemetry: list[bytes] = []  # plain frames at the ground station
        self.refused: list[str] = []
        self.captured: list[bytes] = []  # everything that went ground -> vehicle
        self.notices: list[str] = []  # what the ground end told its operator
        self.lose_down: Callable[[bytes], bool] = lambda raw: False  # drops vehicle -> ground

    def new_ground(self, key: mldsa.MLDSA87PrivateKey = GCS_KEY, **options: Any) -> GroundEnd:
        return GroundEnd(
            Initiator("gcs", key, self.clock), ROBOT_KEM.public_key(), clock=self.clock,
            **options,
        )  # fmt: skip

    def run(self, seconds: float, tick_s: float = 0.1) -> list[tuple[float, int]]:
        """Tick the ground end for ``seconds`` of the manual clock (the air instant): the
        cumulative bytes it handed out after each tick, with the time."""
        out: list[tuple[float, int]] = []
        start = self.clock.monotonic()
        while self.clock.monotonic() - start < seconds:
            self.up(self.ground.tick())
            out.append((self.clock.monotonic() - start, self.ground_bytes()))
            self.clock.advance(tick_s)
        return out

    def ground_bytes(self) -> int:
        """Every byte the ground end handed to the air so far (all kinds)."""
        return sum(self.ground.airtime.values())

    def connect(self) -> None:
        self.up(self.ground.handshake())
        assert self.ground.session is not None

    def up(self, frames: list[bytes]) -> None:
        """Deliver ``frames`` to the vehicle end; answers go back down."""
        self.captured += frames
        self._carry(frames, self.vehicle, self.delivered, self.down)

    def down(self, frames: list[bytes]) -> None:
        """Deliver ``frames`` (but those :attr:`lose_down` drops) to the ground end; answers
        go back up."""
        kept = [raw for raw in frames if not self.lose_down(raw)]
        self._carry(kept, self.ground, self.telemetry, self.up)

    def _carry(
        self,
        frames: list[bytes],
        end: GroundEnd | VehicleEnd,
        local: list[bytes],
        answer: Callable[[list[bytes]], None],
    ) -> None:
        for raw in frames:
            try:
                out = end.from_air(raw)
            except ReplayAttackError as exc:
                self.refused.append(str(exc.code))
                if isinstance(end, VehicleEnd):
                    answer(end.answered())  # a refused HS1's PQ_REFUSAL, as the link sends it
                continue
            local += out.local
            if out.notice is not None:
                self.notices.append(out.notice)
            answer(out.air)

    def commands(self) -> list[dialect.MAVLink_command_long_message]:
        decoder = dialect.MAVLink(Keep())
        return [
            m
            for raw in self.delivered
            if (m := decoder.decode(bytearray(raw))).get_type() == "COMMAND_LONG"
        ]


def blob(frames: list[bytes]) -> bytes:
    """The blob the data chunks among ``frames`` carry, in index order."""
    chunks = [c for raw in frames if not (c := parse_chunk(parse_frame(raw))).is_parity]
    return b"".join(c.piece for c in sorted(chunks, key=lambda c: c.index))


#: A line so fast that the handshake budget never binds (tests of timers, not of airtime).
FAST_AIR_BPS = 100_000_000


def connected(clock: ManualClock, **ground: Any) -> EndPair:
    """Both ends, hand-shaken."""
    made = EndPair(clock, **ground)
    made.connect()
    return made
