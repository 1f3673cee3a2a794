"""MAVLink v2 codec: strict parsing, the sender's timestamps, signing that pymavlink accepts."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay import ManualClock
from antireplay.errors import InvalidFrameError, NonceExhaustedError, SignatureInvalidError
from antireplay.mavlink import TS_LIMIT, MavlinkGuard, TimestampSource, mav_time, sign_frame
from tests.mavlink_frames import KEY, Sink


@pytest.mark.parametrize(
    "bad", [b"", b"\xfd", b"\xfe\x09" + bytes(20), b"\xfd\x09\x00", b"\xfd\x01\x80" + bytes(20)]
)
def test_malformed_frames_are_typed(clock: ManualClock, bad: bytes) -> None:
    with pytest.raises(InvalidFrameError):
        MavlinkGuard(KEY, clock=clock).open(bad)


def test_timestamp_source_tracks_time_and_refuses_wrap(clock: ManualClock) -> None:
    source = TimestampSource(clock)
    a, b = source.next(), source.next()
    assert a == mav_time(clock) and b == a + 1
    clock.advance(1)
    assert source.next() == mav_time(clock)
    with pytest.raises(NonceExhaustedError):
        TimestampSource(clock, last=TS_LIMIT - 1).next()


def test_sign_frame_is_accepted_by_guard_and_pymavlink(clock: ManualClock) -> None:
    plain = dialect.MAVLink(Sink(), srcSystem=255, srcComponent=190)
    plain.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    signed = sign_frame(plain.file.frames[-1], KEY, 4, TimestampSource(clock))
    assert MavlinkGuard(KEY, clock=clock).open(signed).stream == (255, 190, 4)
    receiver = dialect.MAVLink(Sink())
    receiver.signing.secret_key = KEY
    receiver.signing.timestamp = mav_time(clock)
    assert receiver.check_signature(bytearray(signed), 255, 190)
    with pytest.raises(SignatureInvalidError):  # the signature binds the key: another one fails
        MavlinkGuard(bytes(reversed(KEY)), clock=clock).open(signed)
