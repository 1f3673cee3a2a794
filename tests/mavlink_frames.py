"""Signed MAVLink v2 frames for the tests: pymavlink encoders that sign into a list."""

from __future__ import annotations

from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay import ManualClock
from antireplay.mavlink import mav_time

KEY = bytes(range(32))
NOW = 1_800_000_000.0  # the wall time of the ``clock`` fixture (tests/conftest.py)


class Sink:
    """pymavlink's output file, kept in a list."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


def encoder(sysid: int = 255, link_id: int = 1, ts: int | None = None) -> tuple[Any, Sink]:
    """A pymavlink MAVLink object that signs into a list (a GCS without a socket)."""
    sink = Sink()
    mav = dialect.MAVLink(sink, srcSystem=sysid, srcComponent=190)
    mav.signing.secret_key = KEY
    mav.signing.sign_outgoing = True
    mav.signing.link_id = link_id
    mav.signing.timestamp = mav_time(ManualClock(NOW)) if ts is None else ts
    return mav, sink


def command_frame(mav: Any, sink: Sink, target: int = 1, param1: float = 1.0) -> bytes:
    mav.command_long_send(target, 1, 400, 0, param1, 0, 0, 0, 0, 0, 0)
    return sink.frames[-1]


def unsigned_heartbeat(sysid: int) -> bytes:
    plain = dialect.MAVLink(Sink(), srcSystem=sysid, srcComponent=1)
    plain.heartbeat_send(6, 8, 0, 0, 0)
    return bytes(plain.file.frames[-1])
