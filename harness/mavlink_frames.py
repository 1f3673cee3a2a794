"""MAVLink for the tests: pymavlink encoders that sign into a list, frames as a SiK radio
sends them, and an in-process transport."""

from __future__ import annotations

from typing import Any

from pymavlink.dialects.v10 import ardupilotmega as dialect_v1
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay import ManualClock
from antireplay.core.errors import InvalidFrameError
from antireplay.mavlink import mav_time
from antireplay.mavlink.codec import split_parsed
from antireplay.mavlink.endpoints import Transport, parse_endpoint

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


def unsigned_heartbeat(sysid: int, compid: int = 1) -> bytes:
    plain = dialect.MAVLink(Sink(), srcSystem=sysid, srcComponent=compid)
    plain.heartbeat_send(6, 8, 0, 0, 0)
    return bytes(plain.file.frames[-1])


def v1_radio_status() -> bytes:
    """A SiK radio's RADIO_STATUS as MAVLink v1 (system 51), as the radio injects it."""
    radio = dialect_v1.MAVLink(Sink(), srcSystem=51, srcComponent=68)
    radio.radio_status_send(200, 180, 90, 40, 30, 0, 0)
    return bytes(radio.file.frames[-1])


class FakeTransport(Transport):
    """An in-process endpoint: frames are injected, writes are recorded."""

    def __init__(self, text: str, *, fixed: bool = True) -> None:
        super().__init__(parse_endpoint(text), fixed=fixed)
        self.sent: list[tuple[bytes, Any]] = []
        self._deliver: Any = None

    def start(self, deliver: Any) -> None:
        self._deliver = deliver

    def _write(self, data: bytes, peer: Any) -> None:
        self.sent.append((bytes(data), peer))

    def close(self) -> None:
        """Nothing to release."""

    def inject(self, raw: bytes, peer: Any = None) -> None:
        """Deliver ``raw`` as a UDP transport would: parsed, or all its bytes dropped."""
        try:
            frames = split_parsed(raw)
        except InvalidFrameError:
            self._deliver(self, peer, [], len(raw))
            return
        self._deliver(self, peer, frames, 0)
