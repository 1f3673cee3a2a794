"""The simulated vehicle answers only what verifies, and a hostile frame is a counted drop."""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.mavlink.sim import SimVehicle


class _Frames:
    def __init__(self) -> None:
        self.data = b""

    def write(self, data: bytes) -> None:
        self.data += bytes(data)


def test_an_unsigned_or_foreign_frame_is_counted_never_raised() -> None:
    sim = SimVehicle(b"k" * 32, udp=("127.0.0.1", 9))
    out = _Frames()
    unsigned = dialect.MAVLink(out, srcSystem=255, srcComponent=190)
    unsigned.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    foreign = dialect.MAVLink(_Frames(), srcSystem=255, srcComponent=190)
    foreign.signing.secret_key = b"x" * 32
    foreign.signing.sign_outgoing = True
    foreign.signing.timestamp = 1
    foreign.file = out
    frames = [out.data]
    out.data = b""
    foreign.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    frames.append(out.data)
    for frame in frames:
        sim.handle(frame)
    assert sim.counts["command"] == 0
    assert sim.counts["refused"] == 2
