"""MAVLink v2 frames: strict parsing, the signature trailer, the sender's side of signing.

Theory of operation
-------------------
A signed MAVLink v2 frame ends with a 13-byte trailer: ``link_id`` (1 byte), a
48-bit timestamp (10 µs units since 2015-01-01 UTC, little-endian) and the
first 6 bytes of ``SHA-256(key | frame without those 6 bytes)``.

:func:`split_frames` cuts a datagram into frames and :func:`parse_frame` parses
one strictly: v2 only (v1 frames cannot be signed), known incompat flags, exact
length, and the CRC with the dialect's ``crc_extra`` when the message is known;
anything else raises ``INVALID_FRAME``.  Parsing decides nothing else: verifying
the signature and judging the timestamp are the guard's
(:mod:`antireplay.mavlink.guard`).  :func:`target_system` reads a known
message's ``target_system`` field; :func:`claimed_source` reads the source
system and component an audit record names, from any bytes, unauthenticated.

:func:`mav_time` is the wall clock in signing units.  Sender side:
:class:`TimestampSource` keeps a link's timestamp tied to real time
(``max(last + 1, now)``) and raises :class:`NonceExhaustedError` at ``2**48``
instead of truncating; :func:`sign_frame` signs a v2 frame with it.
"""

from __future__ import annotations

import hashlib
import struct
import threading
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as dialect
from pymavlink.generator.mavcrc import x25crc

from antireplay.clock import Clock, resolve
from antireplay.errors import InvalidFrameError, NonceExhaustedError

STX_V2 = 0xFD
SIGNED = 0x01
HEADER = 10
SIG_LEN = 13
MAV_EPOCH = 1_420_070_400  # 2015-01-01T00:00:00Z
TS_LIMIT = 2**48
UNITS_PER_S = 100_000
_HEAD = struct.Struct("<BBBBBBBHB")  # stx len incompat compat seq sys comp msgid(lo16) msgid(hi8)


def mav_time(clock: Clock) -> int:
    """The wall clock in MAVLink signing units (10 µs since 2015-01-01)."""
    return int((clock.wall() - MAV_EPOCH) * UNITS_PER_S)


@dataclass(frozen=True)
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

    @property
    def stream(self) -> tuple[int, int, int]:
        return (self.sysid, self.compid, self.link_id)


def split_frames(datagram: bytes) -> list[bytes]:
    """Cut a datagram into v2 frames; anything malformed raises ``INVALID_FRAME``."""
    frames, at = [], 0
    while at < len(datagram):
        if datagram[at] != STX_V2:
            raise InvalidFrameError("not a MAVLink v2 frame (v1 frames cannot be signed)")
        if len(datagram) - at < HEADER + 2:
            raise InvalidFrameError("truncated header")
        length, incompat = datagram[at + 1], datagram[at + 2]
        total = HEADER + length + 2 + (SIG_LEN if incompat & SIGNED else 0)
        if len(datagram) - at < total:
            raise InvalidFrameError("truncated frame")
        frames.append(bytes(datagram[at : at + total]))
        at += total
    if not frames:
        raise InvalidFrameError("empty datagram")
    return frames


def parse_frame(raw: bytes) -> Frame:
    """Strictly parse one v2 frame (length, flags, CRC for known messages)."""
    if len(raw) < HEADER + 2 or raw[0] != STX_V2:
        raise InvalidFrameError("not a MAVLink v2 frame")
    _, length, incompat, _, _, sysid, compid, lo, hi = _HEAD.unpack_from(raw)
    if incompat & ~SIGNED:
        raise InvalidFrameError("unknown incompatibility flags")
    signed = bool(incompat & SIGNED)
    if len(raw) != HEADER + length + 2 + (SIG_LEN if signed else 0):
        raise InvalidFrameError("frame length does not match its header")
    msgid = lo | hi << 16
    payload = raw[HEADER : HEADER + length]
    spec = dialect.mavlink_map.get(msgid)
    if spec is not None:
        crc = x25crc(raw[1 : HEADER + length])
        crc.accumulate(bytes([spec.crc_extra]))
        if crc.crc != int.from_bytes(raw[HEADER + length : HEADER + length + 2], "little"):
            raise InvalidFrameError("CRC mismatch")
    if not signed:
        return Frame(raw, sysid, compid, msgid, payload, False)
    trailer = raw[-SIG_LEN:]
    timestamp = int.from_bytes(trailer[1:7], "little")
    return Frame(raw, sysid, compid, msgid, payload, True, trailer[0], timestamp)


def target_system(frame: Frame) -> int | None:
    """The frame's ``target_system`` field, if its message (known to the dialect) has one."""
    spec = dialect.mavlink_map.get(frame.msgid)
    if spec is None or "target_system" not in spec.ordered_fieldnames:
        return None
    size = spec.unpacker.size
    payload = frame.payload[:size].ljust(size, b"\0")  # v2 trims trailing zero bytes
    values = spec.unpacker.unpack(payload)
    return int(values[spec.ordered_fieldnames.index("target_system")])


def claimed_source(raw: bytes) -> tuple[int, int] | None:
    """The header's source system and component, unverified (None if too short to hold them)."""
    return (raw[5], raw[6]) if len(raw) > 6 else None


class TimestampSource:
    """A sender's link timestamp tied to real time; never wraps past 2**48."""

    def __init__(self, clock: Clock | None = None, last: int = 0) -> None:
        self.clock = resolve(clock)
        self._last = last
        self._lock = threading.Lock()

    def next(self) -> int:
        with self._lock:
            ts = max(self._last + 1, mav_time(self.clock))
            if ts >= TS_LIMIT:
                raise NonceExhaustedError("MAVLink timestamp reached 2**48; rekey the link")
            self._last = ts
            return ts


def sign_frame(frame: bytes, key: bytes, link_id: int, timestamps: TimestampSource) -> bytes:
    """Sign an unsigned v2 frame of a message known to the dialect."""
    parsed = parse_frame(frame)
    if parsed.signed:
        raise ValueError("frame is already signed")
    spec = dialect.mavlink_map.get(parsed.msgid)
    if spec is None:
        raise ValueError(f"message {parsed.msgid} is not in the dialect")
    head = bytearray(frame[:HEADER])
    head[2] |= SIGNED
    body = bytes(head) + parsed.payload
    crc = x25crc(body[1:])
    crc.accumulate(bytes([spec.crc_extra]))
    checksum: int = crc.crc
    signed = body + checksum.to_bytes(2, "little")
    signed += bytes([link_id]) + timestamps.next().to_bytes(6, "little")
    return signed + hashlib.sha256(key + signed).digest()[:6]
