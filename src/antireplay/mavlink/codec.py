"""MAVLink frames: strict parsing, stream framing, the signature trailer, signing.

Theory of operation
-------------------
A signed MAVLink v2 frame ends with a 13-byte trailer: ``link_id`` (1 byte), a
48-bit timestamp (10 µs units since 2015-01-01 UTC, little-endian) and the
first 6 bytes of ``SHA-256(key | frame without those 6 bytes)``.

:func:`split_frames` cuts a datagram into frames (all of it, or it is refused:
a datagram is never resynchronised) and :func:`parse_frame` parses one strictly:
known incompat flags, exact length, and the CRC with the dialect's ``crc_extra``
when the message is known; anything else raises ``INVALID_FRAME``.
A MAVLink v1 frame (``0xFE``) parses too, as an unsigned frame with
``version == 1`` (v1 cannot be signed; the guard takes it only where listed).
:class:`FrameReader` cuts a byte stream (serial, TCP) into frames the way
flight-stack parsers do: it skips bytes until a start marker, waits for the
whole frame (a v2 header with unknown incompat flags is a false start at once),
and on a CRC mismatch drops one byte and resynchronises; it never
buffers more than one frame, so a flood of garbage costs linear work and no
memory.  Parsing decides nothing else: verifying the signature and judging the
timestamp are the guard's (:mod:`antireplay.mavlink.guard`).  :func:`target`
reads a known message's ``target_system``/``target_component`` fields;
:func:`claimed_source` reads the source system and component an audit record
names, from any bytes, unauthenticated.  :func:`passphrase_key` derives a link
key from a passphrase as MAVProxy, QGroundControl and Mission Planner do
(SHA-256 of the passphrase).

:func:`mav_time` is a clock's wall time in signing units.  :func:`sign_frame`
(:func:`sign`: the signed :class:`Frame`) signs a v2 frame with a link's next
timestamp (:mod:`antireplay.mavlink.signing`, :mod:`antireplay.mavlink.signer`);
a signed frame is signed again: a router forwarding between links with different
keys.  The key is 32 bytes, or a :class:`KeyedDigest` (a key in a PKCS#11 token that
computes the signature's SHA-256 itself).  :func:`split_parsed` and
:meth:`FrameReader.feed_parsed` hand out the parsed frames, so that a frame is parsed
once on its way through a router.
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass
from functools import cache
from typing import Protocol

from fastcrc.crc16 import mcrf4xx
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.core.clock import Clock
from antireplay.core.errors import InvalidFrameError

STX_V2 = 0xFD
STX_V1 = 0xFE
SIGNED = 0x01
HEADER = 10
HEADER_V1 = 6
MAX_FRAME = HEADER + 255 + 2 + 13
SIG_LEN = 13
MAV_EPOCH = 1_420_070_400  # 2015-01-01T00:00:00Z
TS_LIMIT = 2**48
UNITS_PER_S = 100_000
_HEAD = struct.Struct("<BBBBBBBHB")  # stx len incompat compat seq sys comp msgid(lo16) msgid(hi8)
_TRAILER = struct.Struct("<BIH")  # link id, timestamp (low 32 bits, high 16 bits)
_V1_START = bytes((STX_V1,))
_STARTS = (STX_V2, STX_V1)


def mav_time(clock: Clock) -> int:
    """The wall clock in MAVLink signing units (10 µs since 2015-01-01)."""
    return int((clock.wall() - MAV_EPOCH) * UNITS_PER_S)


@dataclass(frozen=True, slots=True)
class Frame:
    """One parsed MAVLink v2 frame."""

    raw: bytes
    sysid: int
    compid: int
    msgid: int
    payload: bytes
    signed: bool
    link_id: int = 0
    timestamp: int = 0
    version: int = 2

    @property
    def stream(self) -> tuple[int, int, int]:
        return (self.sysid, self.compid, self.link_id)


def split_frames(datagram: bytes) -> list[bytes]:
    """Cut a datagram into whole frames (v1 or v2), each parsed strictly (:func:`split_parsed`)."""
    return [frame.raw for frame in split_parsed(datagram)]


def split_parsed(datagram: bytes) -> list[Frame]:
    """Cut a datagram into whole frames (v1 or v2), each parsed strictly.  A datagram is
    judged alone, never resynchronised: a byte before, between or after its frames, or a
    frame cut short, raises ``INVALID_FRAME`` for the whole datagram."""
    size = len(datagram)
    if (
        size > 2
        and datagram[0] in _STARTS
        and frame_length(datagram) == size
        and isinstance(datagram, bytes)
    ):
        return [parse_frame(datagram)]  # one frame, the common case: no copy
    frames: list[Frame] = []
    at = 0
    while at < size:
        if datagram[at] not in (STX_V2, STX_V1):
            raise InvalidFrameError(f"byte {at} of the datagram is no MAVLink start marker")
        length = frame_length(datagram, at)
        if length is None or len(datagram) - at < length:
            raise InvalidFrameError(f"truncated frame at byte {at} of the datagram")
        frames.append(parse_frame(bytes(datagram[at : at + length])))
        at += length
    if not frames:
        raise InvalidFrameError("empty datagram")
    return frames


def frame_length(data: bytes | bytearray, at: int = 0) -> int | None:
    """The length of the frame starting at ``data[at]`` (a start marker), if its header is in."""
    if data[at] == STX_V1:
        return HEADER_V1 + data[at + 1] + 2 if len(data) - at >= 2 else None
    if len(data) - at < 3:
        return None
    return HEADER + data[at + 1] + 2 + (SIG_LEN if data[at + 2] & SIGNED else 0)


class FrameReader:
    """Cuts a byte stream into frames (module docstring); not thread-safe (one per stream)."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        #: Bytes skipped while resynchronising (garbage, corrupt frames), for the caller's count.
        self.skipped = 0

    @property
    def pending(self) -> int:
        """Bytes held for a frame not yet complete (at most one frame)."""
        return len(self._buffer)

    def feed(self, data: bytes) -> list[bytes]:
        """Append ``data``; return the complete frames (v1 or v2) it finished."""
        return [frame.raw for frame in self.feed_parsed(data)]

    def feed_parsed(self, data: bytes) -> list[Frame]:
        """:meth:`feed`, as the parsed frames."""
        buffer: bytearray = self._buffer
        frames: list[Frame] = []
        buffer += data
        while buffer:
            start = _next_start(buffer)
            if start:
                self.skipped += start
                del buffer[:start]
                continue
            if buffer[0] == STX_V2 and len(buffer) >= 3 and buffer[2] & ~SIGNED:
                self.skipped += 1  # unknown incompat flags: a false start, known at once
                del buffer[:1]
                continue
            length = frame_length(buffer)
            if length is None or len(buffer) < length:
                break
            try:
                frame = parse_frame(bytes(buffer[:length]))
            except InvalidFrameError:
                self.skipped += 1  # a false start or a corrupt frame: resynchronise
                del buffer[:1]
                continue
            frames.append(frame)
            del buffer[:length]
        return frames


def _next_start(buffer: bytearray) -> int:
    """Offset of the first start marker (the whole length if there is none)."""
    found = [at for at in (buffer.find(STX_V2), buffer.find(STX_V1)) if at >= 0]
    return min(found) if found else len(buffer)


def _parse_v1(raw: bytes) -> Frame:
    if len(raw) < HEADER_V1 + 2 or len(raw) != HEADER_V1 + raw[1] + 2:
        raise InvalidFrameError("MAVLink v1 frame length does not match its header")
    sysid, compid, msgid = raw[3], raw[4], raw[5]
    payload = raw[HEADER_V1:-2]
    extra = _CRC_EXTRA.get(msgid)
    if extra is not None and _crc(raw, len(raw) - 2, extra) != int.from_bytes(raw[-2:], "little"):
        raise InvalidFrameError("CRC mismatch")
    return Frame(raw, sysid, compid, msgid, payload, False, version=1)


def parse_frame(raw: bytes) -> Frame:
    """Strictly parse one frame (length, flags, CRC for known messages); v1 is unsigned."""
    if raw[:1] == _V1_START:
        return _parse_v1(raw)
    if len(raw) < HEADER + 2 or raw[0] != STX_V2:
        raise InvalidFrameError("not a MAVLink frame")
    _, length, incompat, _, _, sysid, compid, lo, hi = _HEAD.unpack_from(raw)
    if incompat & ~SIGNED:
        raise InvalidFrameError("unknown incompatibility flags")
    signed = bool(incompat & SIGNED)
    if len(raw) != HEADER + length + 2 + (SIG_LEN if signed else 0):
        raise InvalidFrameError("frame length does not match its header")
    msgid = lo | hi << 16
    payload = raw[HEADER : HEADER + length]
    end = HEADER + length
    extra = _CRC_EXTRA.get(msgid)
    if extra is not None and _crc(raw, end, extra) != int.from_bytes(raw[end : end + 2], "little"):
        raise InvalidFrameError("CRC mismatch")
    if not signed:
        return Frame(raw, sysid, compid, msgid, payload, False)
    link_id, lo32, hi16 = _TRAILER.unpack_from(raw, len(raw) - SIG_LEN)
    return Frame(raw, sysid, compid, msgid, payload, True, link_id, lo32 | hi16 << 32)


def target(frame: Frame) -> tuple[int | None, int | None]:
    """The frame's ``target_system`` and ``target_component`` fields, where its message
    (known to the dialect) has them; None where it has not (a broadcast)."""
    layout = _target_layout(frame.msgid)
    if layout is None:
        return None, None
    unpacker, system, component = layout
    size = unpacker.size
    payload = frame.payload[:size].ljust(size, b"\0")  # v2 trims trailing zero bytes
    values = unpacker.unpack(payload)
    return int(values[system]), None if component is None else values[component]


#: Each known message's ``crc_extra``: the byte a frame's CRC ends with.
_CRC_EXTRA: dict[int, int] = {m: spec.crc_extra for m, spec in dialect.mavlink_map.items()}
_BYTE = tuple(bytes((i,)) for i in range(256))  # each byte value, made once


def _crc(raw: bytes | bytearray, end: int, extra: int) -> int:
    """CRC-16/MCRF4XX (MAVLink's X.25) of ``raw[1:end]`` and ``extra``, as pymavlink's
    ``x25crc`` computes it, in calls of its own native dependency (on a view: no copy)."""
    return mcrf4xx(_BYTE[extra], mcrf4xx(memoryview(raw)[1:end], 0xFFFF))


@cache
def _target_layout(msgid: int) -> tuple[struct.Struct, int, int | None] | None:
    """Where message ``msgid``'s target fields are in its unpacked payload (None: it has no
    ``target_system``, or the dialect does not know it); read once per message id."""
    spec = dialect.mavlink_map.get(msgid)
    names = () if spec is None else spec.ordered_fieldnames
    if "target_system" not in names:
        return None
    component = names.index("target_component") if "target_component" in names else None
    return spec.unpacker, names.index("target_system"), component


def target_system(frame: Frame) -> int | None:
    """The frame's ``target_system`` field, if its message (known to the dialect) has one."""
    return target(frame)[0]


def claimed_source(raw: bytes) -> tuple[int, int] | None:
    """The header's source system and component, unverified (None if too short to hold them)."""
    if raw[:1] == bytes([STX_V1]):
        return (raw[3], raw[4]) if len(raw) > 4 else None
    return (raw[5], raw[6]) if len(raw) > 6 else None


def passphrase_key(passphrase: str) -> bytes:
    """The 32-byte link key for a passphrase: SHA-256 of its bytes (MAVProxy's
    ``signing key PASSPHRASE``, QGroundControl, Mission Planner)."""
    return hashlib.sha256(passphrase.encode()).digest()


class Timestamps(Protocol):
    """What signs with: the next timestamp of a link (:class:`~.signer.TimestampSource`)."""

    def next(self) -> int: ...


class KeyedDigest(Protocol):
    """A link key that never leaves its token: ``SHA-256(key || data)`` computed there
    (C_DigestKey; :class:`antireplay.keys.pkcs11.TokenDigestKey`)."""

    def digest(self, data: bytes, /) -> bytes: ...


def sign_frame(
    frame: bytes | Frame, key: bytes | KeyedDigest, link_id: int, timestamps: Timestamps
) -> bytes:
    """Sign a v2 frame of a message known to the dialect with ``key``; a signed frame is
    signed again (a router forwarding between links with different keys)."""
    return sign(frame, key, link_id, timestamps).raw


def sign(
    frame: bytes | Frame, key: bytes | KeyedDigest, link_id: int, timestamps: Timestamps
) -> Frame:
    """:func:`sign_frame`, as the parsed :class:`Frame` of the signed bytes (built, not
    parsed again)."""
    parsed = frame if isinstance(frame, Frame) else parse_frame(frame)
    if parsed.version != 2:
        raise ValueError("a MAVLink v1 frame cannot be signed")
    spec = dialect.mavlink_map.get(parsed.msgid)
    if spec is None:
        raise ValueError(f"message {parsed.msgid} is not in the dialect")
    head = bytearray(parsed.raw[:HEADER])
    head[2] |= SIGNED
    body = bytes(head) + parsed.payload
    signed = body + _crc(body, len(body), spec.crc_extra).to_bytes(2, "little")
    timestamp = timestamps.next()
    signed += _TRAILER.pack(link_id, timestamp & 0xFFFFFFFF, timestamp >> 32)
    keyed = hashlib.sha256(key + signed).digest() if isinstance(key, bytes) else key.digest(signed)
    signed += keyed[:6]
    return Frame(
        signed, parsed.sysid, parsed.compid, parsed.msgid, parsed.payload, True, link_id, timestamp
    )
