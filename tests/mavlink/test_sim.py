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


def _setup_signing(
    key: bytes, timestamp: int, signer: bytes | None, signed_at: int | None = None
) -> bytes:
    out = _Frames()
    mav = dialect.MAVLink(out, srcSystem=255, srcComponent=190)
    if signer is not None:
        mav.signing.secret_key, mav.signing.sign_outgoing = signer, True
        mav.signing.timestamp = signed_at or timestamp  # fresh: the vehicle's own time
    mav.setup_signing_send(1, 1, list(key), timestamp)
    return out.data


def test_setup_signing_is_taken_as_ardupilot_takes_it() -> None:
    """Key and timestamp taken at once; ignored while armed (the issue's rule); an all-zero
    key turns signing off only with a zero timestamp, as in GCS_Signing.cpp."""
    sim = SimVehicle(None, udp=("127.0.0.1", 9))
    assert sim.key is None  # never provisioned: signs nothing
    sim.armed = True
    sim.handle(_setup_signing(b"n" * 32, 2**40, None))
    assert (sim.key, sim.counts["setup_refused_armed"]) == (None, 1)
    sim.armed = False
    sim.handle(_setup_signing(b"n" * 32, 2**40, None))
    assert sim.key == b"n" * 32 and sim.mav.signing.timestamp >= 2**40
    sim.handle(_setup_signing(b"m" * 32, 2**40, None))  # unsigned: signing is on now
    assert sim.key == b"n" * 32
    sim.handle(_setup_signing(bytes(32), sim.mav.signing.timestamp + 100, b"n" * 32))
    assert sim.key == bytes(32) and sim.mav.signing.sign_outgoing  # a timestamp: a key
    sim.handle(_setup_signing(bytes(32), 0, bytes(32), sim.mav.signing.timestamp + 200))
    assert sim.key is None and not sim.mav.signing.sign_outgoing
