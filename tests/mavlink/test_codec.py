"""MAVLink v2 codec: strict parsing, the sender's timestamps, signing that pymavlink accepts."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as dialect
from pymavlink.generator.mavcrc import x25crc

from antireplay import ManualClock
from antireplay.core.errors import (
    InvalidFrameError,
    SignatureInvalidError,
    SignatureRequiredError,
)
from antireplay.mavlink import (
    FrameReader,
    MavlinkGuard,
    TimestampSource,
    claimed_source,
    codec,
    mav_time,
    parse_frame,
    passphrase_key,
    sign_frame,
)
from harness.mavlink_frames import KEY, Sink, command_frame, encoder, v1_radio_status


@pytest.mark.parametrize(
    "bad", [b"", b"\xfd", b"\xfe\x09" + bytes(20), b"\xfd\x09\x00", b"\xfd\x01\x80" + bytes(20)]
)
def test_malformed_frames_are_typed(clock: ManualClock, bad: bytes) -> None:
    with pytest.raises(InvalidFrameError):
        MavlinkGuard(KEY, clock=clock).open(bad)


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


def test_passphrase_key_is_mavproxys() -> None:
    from MAVProxy.modules.mavproxy_signing import SigningModule  # noqa: PLC0415

    for phrase in ("secret", "correct-horse-battery-staple"):
        assert passphrase_key(phrase) == SigningModule.passphrase_to_key(None, phrase)


def test_v1_frames_parse_unsigned_and_pass_only_where_listed(clock: ManualClock) -> None:
    raw = v1_radio_status()
    frame = parse_frame(raw)
    assert (frame.version, frame.signed, frame.sysid, frame.msgid) == (1, False, 51, 109)
    assert claimed_source(raw) == (51, 68)
    with pytest.raises(InvalidFrameError):
        parse_frame(raw[:-1] + bytes([raw[-1] ^ 1]))  # the CRC covers v1 frames too
    with pytest.raises(SignatureRequiredError, match="v1"):
        MavlinkGuard(KEY, clock=clock, allow_unsigned=frozenset({109})).open(raw)
    allowed = MavlinkGuard(
        KEY, clock=clock, allow_unsigned=frozenset({109}), allow_v1=frozenset({109})
    )
    assert not allowed.open(raw).signed
    with pytest.raises(ValueError, match="v1"):
        sign_frame(raw, KEY, 1, TimestampSource(clock))


def test_frame_reader_cuts_a_stream_and_resynchronises() -> None:
    mav, sink = encoder()
    frames = [command_frame(mav, sink, param1=float(i)) for i in range(3)]
    corrupt = bytearray(frames[1])
    corrupt[20] ^= 0xFF  # a CRC mismatch: dropped, the reader finds the next frame
    stream = b"\x00garbage\xfd" + frames[0] + bytes(corrupt) + v1_radio_status() + frames[2]
    reader, out = FrameReader(), []
    for at in range(0, len(stream), 7):  # any chunking, as a serial port delivers
        out += reader.feed(stream[at : at + 7])
    assert out == [frames[0], v1_radio_status(), frames[2]]
    assert reader.skipped == 9 + len(corrupt) and reader.pending == 0
    assert FrameReader().feed(b"\xfd" * 5_000) == []  # a flood buffers at most one frame


@given(st.binary(min_size=1, max_size=300), st.integers(0, 255))
def test_the_frame_crc_is_pymavlinks_x25(data: bytes, extra: int) -> None:
    """The parser's one-call CRC (fastcrc's MCRF4XX) equals pymavlink's ``x25crc``."""
    reference = x25crc(data[1:])
    reference.accumulate(bytes([extra]))
    assert codec._crc(data, len(data), extra) == reference.crc


def test_target_fields_are_read_per_message_layout() -> None:
    """``target`` reads COMMAND_LONG's target system and component, and None for a message
    without them (HEARTBEAT), from the cached layout."""
    mav = dialect.MAVLink(None, srcSystem=255, srcComponent=190)
    command = bytes(mav.command_long_encode(7, 3, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(mav))
    heartbeat = bytes(mav.heartbeat_encode(6, 8, 0, 0, 0).pack(mav))
    assert codec.target(codec.parse_frame(command)) == (7, 3)
    assert codec.target(codec.parse_frame(heartbeat)) == (None, None)
