"""The air format: the dialect's messages, MAVLink v2 packing, compact session frames.

See :mod:`antireplay.mavlink.pq` for the theory of operation.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from enum import IntEnum
from importlib import resources
from typing import Protocol

from pymavlink.dialects.v20 import ardupilotmega as dialect
from pymavlink.generator import mavparse
from pymavlink.generator.mavcrc import x25crc

from antireplay.core.errors import (
    Code,
    InvalidFrameError,
    ReplayAttackError,
    SignatureInvalidError,
    UnknownSessionError,
)
from antireplay.mavlink.codec import HEADER, STX_V2, Frame
from antireplay.pq.session import (
    FRAME_MAGIC,
    VERSION,
    Direction,
    Opened,
    Session,
)

MSG_CHUNK, MSG_STATUS, MSG_REPAIR, MSG_REFUSAL = 61000, 61001, 61002, 61003
CHUNK_DATA, CHUNK_MAC, MAX_CHUNKS = 249, 8, 32
#: Parity chunks after a blob's data chunks: one per ``PARITY_EVERY`` (rounded up), at most
#: ``MAX_PARITY``; parity chunk ``j`` is the XOR of the data chunks whose index is ``j``
#: modulo the parity count, so one loss in each such group costs no round trip.
MAX_PARITY, PARITY_EVERY = 4, 10
#: Bits a byte takes on a radio's serial line (start, 8 data, stop): ``--air-bps`` is baud.
LINE_BITS = 10
#: Airtime a failing handshake may take (the ground end's HS1s, POKEs and HS1 repairs; the
#: vehicle end's refusals): over any window of ``W`` seconds, at most ``HANDSHAKE_SHARE`` of
#: ``--air-bps`` (``DEFAULT_AIR_BPS``, a SiK radio's, when unset) times ``W``, plus one HS1
#: with its parity (the bucket's burst: about 7.5 KB), so the long-run share is at most
#: ``HANDSHAKE_SHARE`` at every line rate.  Attempts back off from ``retry_s``, doubling up
#: to ``MAX_BACKOFF_S``.
HANDSHAKE_SHARE, DEFAULT_AIR_BPS = 0.05, 57_600
MAX_BACKOFF_S = 60.0
#: An HS1 on the air with its parity, the longest identity's (about 7.5 KB with a short one).
HS1_AIR_BYTES = 8_000
#: A command's age stamp, sealed after its inner frame: ms since its session came up at the
#: ground end (:mod:`.ground` writes it, :mod:`.vehicle` judges it).
AGE_STAMP = struct.Struct("<I")
STATUS_NO_SESSION = 1
#: A ground end rekeys once its session used this many transfer numbers, and stops
#: sending in it at ``TRANSFER_LIMIT``: within a session they never wrap (module docstring).
REKEY_TRANSFERS, TRANSFER_LIMIT = 30_000, 32_000
MAX_SENDER_KEYS = 16  # (sender, chunk key) pairs whose newest opened transfer is kept
_INNER_HEAD = 6
_FRAME = struct.Struct(">BBBB16sQ")  # a session frame's header (antireplay.pq.session)
_COMPACT = struct.Struct(">BBQ")  # handle purpose counter: the header as it travels
_CHUNK = struct.Struct("<HBBBB")  # transfer index count len kind; then data[249]
_V2_HEAD = struct.Struct("<BBBBBBBHB")
_REFUSAL = struct.Struct("<H8sBBB64s16s")  # PQ_REFUSAL in wire order (fields by size)
#: Why a vehicle end refuses an HS1 (``PQ_REFUSAL.code``): the refusal code it counts, and
#: what the ground end's operator should check.
REFUSALS: dict[int, tuple[Code, str]] = {
    1: (Code.SIGNATURE_INVALID, "check --signing-key here and the vehicle's --peer"),
    2: (Code.UNKNOWN_SENDER, "check --identity here and the vehicle's --peer NAME"),
    3: (Code.MESSAGE_STALE, "check both clocks: the vehicle judges HS1 by its wall clock"),
}
REFUSAL_OF = {code: number for number, (code, _) in REFUSALS.items()}
_AGED = re.compile(r"message is (-?[0-9.]+)s old")  # a stale refusal's reason


def _load_dialect() -> dict[int, tuple[int, int]]:
    """``{msgid: (crc_extra, payload length)}`` from the published XML, by pymavlink."""
    xml = resources.files("antireplay.mavlink").joinpath("antireplay_pq.xml")
    with resources.as_file(xml) as path:
        parsed = mavparse.MAVXML(str(path), mavparse.PROTOCOL_2_0)
    return {m.id: (m.crc_extra, m.wire_length) for m in parsed.message}


DIALECT = _load_dialect()
DIALECT_XML = "antireplay_pq.xml"


def share_rate(air_bps: int | None) -> float:
    """Bytes a second a failing handshake may take on a radio of ``air_bps`` baud."""
    if air_bps is not None and air_bps <= 0:
        raise ValueError(f"air_bps must be positive (baud), not {air_bps}")
    return HANDSHAKE_SHARE * (air_bps or DEFAULT_AIR_BPS) / LINE_BITS


def handshake_ttl_s(air_bps: int | None) -> float:
    """How long an HS1 is reassembled and held for repair (at least 10 s): twice its time on
    a radio of ``air_bps`` baud and 5 s more, so a slow line's HS1 arrives whole and its
    NACK is answered (1,200 baud: 138 s; 7,200: 27 s)."""
    airtime = LINE_BITS * HS1_AIR_BYTES / (air_bps or DEFAULT_AIR_BPS)
    return max(10.0, 2 * airtime + 5.0)


def parity_for(count: int) -> int:
    """How many parity chunks follow ``count`` data chunks (none for a one-chunk blob)."""
    return 0 if count < 2 else min(MAX_PARITY, -(-count // PARITY_EVERY))


class ChunkKind(IntEnum):
    """What a chunked blob is (module docstring)."""

    HS1 = 1
    HS2 = 2
    FRAME = 3
    FRAME_CHUNKED = 4


#: Messages signed with ML-DSA-87 (``command`` frames): whatever changes what the vehicle
#: does, including missions, parameters, guided setpoints, file transfer (scripts, logs)
#: and the serial shell; the rest travels HMAC-protected.  The vehicle end refuses any of
#: them in a data frame (``SIGNATURE_REQUIRED``).
SIGNED_MESSAGES = frozenset(
    {
        dialect.MAVLINK_MSG_ID_COMMAND_LONG,
        dialect.MAVLINK_MSG_ID_COMMAND_INT,
        dialect.MAVLINK_MSG_ID_SET_MODE,
        dialect.MAVLINK_MSG_ID_PARAM_SET,
        dialect.MAVLINK_MSG_ID_PARAM_EXT_SET,
        dialect.MAVLINK_MSG_ID_MISSION_COUNT,
        dialect.MAVLINK_MSG_ID_MISSION_ITEM,
        dialect.MAVLINK_MSG_ID_MISSION_ITEM_INT,
        dialect.MAVLINK_MSG_ID_MISSION_WRITE_PARTIAL_LIST,
        dialect.MAVLINK_MSG_ID_MISSION_CLEAR_ALL,
        dialect.MAVLINK_MSG_ID_MISSION_SET_CURRENT,
        dialect.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED,
        dialect.MAVLINK_MSG_ID_SET_POSITION_TARGET_GLOBAL_INT,
        dialect.MAVLINK_MSG_ID_SET_ATTITUDE_TARGET,
        dialect.MAVLINK_MSG_ID_SET_ACTUATOR_CONTROL_TARGET,
        dialect.MAVLINK_MSG_ID_SET_HOME_POSITION,
        dialect.MAVLINK_MSG_ID_SET_GPS_GLOBAL_ORIGIN,
        dialect.MAVLINK_MSG_ID_FILE_TRANSFER_PROTOCOL,
        dialect.MAVLINK_MSG_ID_SERIAL_CONTROL,
        dialect.MAVLINK_MSG_ID_LOG_ERASE,
    }
)


def pack_v2(
    msgid: int, payload: bytes, crc_extra: int, *, sysid: int, compid: int, seq: int
) -> bytes:
    """An unsigned MAVLink v2 frame, trailing zero bytes trimmed as the spec asks."""
    body = payload.rstrip(b"\0") or payload[:1]
    head = _V2_HEAD.pack(
        STX_V2, len(body), 0, 0, seq & 0xFF, sysid, compid, msgid & 0xFFFF, msgid >> 16
    )
    crc = x25crc(head[1:] + body)
    crc.accumulate(bytes([crc_extra]))
    checksum: int = crc.crc
    return head + body + checksum.to_bytes(2, "little")


def status_frame(code: int, sysid: int, compid: int, seq: int = 0) -> bytes:
    """A ``PQ_STATUS`` frame (the vehicle end's unauthenticated hint)."""
    return pack_v2(
        MSG_STATUS, bytes([code]), DIALECT[MSG_STATUS][0], sysid=sysid, compid=compid, seq=seq
    )


@dataclass(frozen=True)
class Refusal:
    """A parsed ``PQ_REFUSAL``: the vehicle end's word that one HS1 opened no session."""

    transfer: int
    hs1_hash: bytes
    target: tuple[int, int]
    code: int
    reason: str
    mac: bytes

    def names(self, hs1: bytes) -> bool:
        """Whether this says it refuses ``hs1`` (by hash; nothing verified yet)."""
        return hmac.compare_digest(self.hs1_hash, hashlib.sha256(hs1).digest()[:8])

    def verify(self, hs1: bytes, key: bytes) -> bool:
        """Whether this refuses exactly ``hs1`` (its hash, not another attempt's) under the
        refusal key that HS1's KEM secret gives (:func:`antireplay.pq.session.refusal_key`)."""
        digest = hashlib.sha256(hs1).digest()
        if not self.names(hs1):
            return False
        fields = _refusal_fields(self.transfer, self.target, self.code, self.reason)
        return hmac.compare_digest(self.mac, _refusal_mac(key, digest, fields))

    @property
    def explained(self) -> str:
        """The reason with what to check, as the ground end logs it."""
        code, hint = REFUSALS.get(self.code, (Code.INVALID_FRAME, "an unknown refusal code"))
        return f"{self.reason or code} ({hint})"

    def explained_after(self, held_s: float, slack_s: float) -> str:
        """:attr:`explained`, told better for a stale HS1 (``MESSAGE_STALE``) that left the
        ground end ``held_s`` ago: the vehicle's age for it about that long (within
        ``slack_s``: its airtime and the clocks' slack) means it was held on the link, not
        that the clocks disagree, and the operator is told so; otherwise the difference."""
        aged = _AGED.search(self.reason) if self.code == REFUSAL_OF[Code.MESSAGE_STALE] else None
        if aged is None:
            return self.explained
        off = float(aged.group(1)) - held_s
        if abs(off) <= slack_s:
            return (
                f"{self.reason} (this HS1 left here {held_s:.1f} s before: it was delayed on"
                " the link, not a clock problem)"
            )
        return (
            f"{self.reason} (the vehicle's clock reads it {off:+.1f} s older than this"
            " end's: check both clocks; the vehicle judges HS1 by its wall clock)"
        )


def _refusal_fields(transfer: int, target: tuple[int, int], code: int, reason: str) -> bytes:
    return struct.pack("<HBBB", transfer, *target, code) + reason.encode("ascii")


def _refusal_mac(key: bytes, digest: bytes, fields: bytes) -> bytes:
    return hmac.digest(key, digest + fields, "sha256")[:16]


def refusal_frame(
    hs1: bytes, key: bytes, *, transfer: int, target: tuple[int, int], code: int, reason: str,
    sysid: int, compid: int,
) -> bytes:  # fmt: skip
    """A ``PQ_REFUSAL`` of ``hs1`` (sent as transfer ``transfer`` by ``target``) under
    ``key`` (its refusal key)."""
    text = "".join(c for c in reason if " " <= c <= "~")[:64]
    digest = hashlib.sha256(hs1).digest()
    mac = _refusal_mac(key, digest, _refusal_fields(transfer, target, code, text))
    payload = _REFUSAL.pack(transfer, digest[:8], *target, code, text.encode("ascii"), mac)
    crc_extra = DIALECT[MSG_REFUSAL][0]
    return pack_v2(MSG_REFUSAL, payload, crc_extra, sysid=sysid, compid=compid, seq=0)


def parse_refusal(frame: Frame) -> Refusal:
    """A ``PQ_REFUSAL`` frame's fields (CRC checked; the MAC is :meth:`Refusal.verify`'s)."""
    transfer, digest, system, component, code, text, mac = _REFUSAL.unpack(_payload_of(frame))
    reason = text.rstrip(b"\0").decode("ascii", "replace")
    reason = "".join(c for c in reason if " " <= c <= "~")
    return Refusal(transfer, digest, (system, component), code, reason, mac)


def _payload_of(frame: Frame) -> bytes:
    """``frame``'s payload at full length (zero-padded), after checking its CRC with ours."""
    crc_extra, length = DIALECT[frame.msgid]
    crc = x25crc(frame.raw[1 : HEADER + len(frame.payload)])
    crc.accumulate(bytes([crc_extra]))
    end = HEADER + len(frame.payload)
    if crc.crc != int.from_bytes(frame.raw[end : end + 2], "little"):
        raise InvalidFrameError("CRC mismatch")
    if len(frame.payload) > length:
        raise InvalidFrameError("payload longer than the message")
    return frame.payload.ljust(length, b"\0")


def read_status(frame: Frame) -> int:
    """The code of a ``PQ_STATUS`` frame (CRC checked)."""
    return _payload_of(frame)[0]


def inner_of(frame: Frame) -> bytes:
    """The inner of a plain MAVLink v2 message (module docstring); a message the dialect
    does not know is refused here, before anything is sealed (the far end could not
    rebuild it)."""
    if frame.msgid not in dialect.mavlink_map:
        raise InvalidFrameError(f"message {frame.msgid} is not in the dialect")
    head = bytes([frame.sysid, frame.compid, frame.raw[4]]) + frame.msgid.to_bytes(3, "little")
    return head + frame.payload


def plain_frame(inner: bytes) -> bytes:
    """The unsigned MAVLink v2 frame an inner describes (a message the dialect knows)."""
    if not _INNER_HEAD <= len(inner) <= _INNER_HEAD + 255:
        raise InvalidFrameError("inner message out of bounds")
    msgid = int.from_bytes(inner[3:6], "little")
    spec = dialect.mavlink_map.get(msgid)
    if spec is None:
        raise InvalidFrameError(f"message {msgid} is not in the dialect")
    payload, crc_extra = inner[_INNER_HEAD:], spec.crc_extra
    return pack_v2(msgid, payload, crc_extra, sysid=inner[0], compid=inner[1], seq=inner[2])


def compact(frame: bytes) -> bytes:
    """A session frame as it travels: magic, version and direction dropped (implied), the
    16-byte session id cut to a 1-byte handle (its last byte)."""
    _, _, purpose, _, sid, counter = _FRAME.unpack_from(frame)
    return _COMPACT.pack(sid[-1], purpose, counter) + frame[_FRAME.size :]


def expand(air: bytes, sessions: Iterable[Session], direction: Direction) -> list[bytes]:
    """The session frames a compact frame can be: one per live session with its handle."""
    if len(air) < _COMPACT.size:
        raise InvalidFrameError("session frame too short")
    handle, purpose, counter = _COMPACT.unpack_from(air)
    rest = air[_COMPACT.size :]
    return [
        _FRAME.pack(FRAME_MAGIC, VERSION, purpose, direction, s.session_id, counter) + rest
        for s in sessions
        if s.session_id[-1] == handle
    ]


class FrameOpener(Protocol):
    """What opens session frames: a :class:`~antireplay.pq.session.Session` or a
    :class:`~antireplay.pq.session.Responder` (``check`` records nothing, ``open`` commits)."""

    def check(self, frame: bytes) -> None: ...

    def open(self, frame: bytes) -> Opened: ...


def open_compact(
    air: bytes, sessions: Iterable[Session], direction: Direction, receiver: FrameOpener
) -> Opened:
    """Open a compact frame under the live session its tag verifies in; typed errors
    otherwise.  A handle shared by two sessions (the vehicle end avoids it, but cannot
    always) is resolved by the tag, never by a window: every candidate is ``check`` ed
    (cheap, records nothing), those that pass are opened newest first (check,
    authenticate, commit, each under its own session), so another session's counters
    can never refuse this one's frames.  When none authenticates, a window refusal
    outranks ``SIGNATURE_INVALID`` (it names a replay)."""
    candidates = expand(air, sessions, direction)
    if not candidates:
        raise UnknownSessionError("no live session with this handle; handshake again")
    if len(candidates) == 1:
        return receiver.open(candidates[0])
    refused: ReplayAttackError | None = None
    fresh = []
    for frame in reversed(candidates):
        try:
            receiver.check(frame)
        except ReplayAttackError as exc:
            refused = refused or exc
            continue
        fresh.append(frame)
    for frame in fresh:
        try:
            return receiver.open(frame)
        except SignatureInvalidError as exc:
            refused = refused or exc
    assert refused is not None
    raise refused
