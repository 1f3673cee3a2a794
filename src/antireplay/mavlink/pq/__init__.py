"""Post-quantum sessions over MAVLink v2: the carriage (dialect, chunks, reassembly, two ends).

Theory of operation
-------------------
:mod:`antireplay.pq.session` makes the blobs (HS1, HS2, session frames); this module
carries them in MAVLink v2 messages of a two-message dialect of ours,
``antireplay_pq.xml`` (published next to this module, ids 61000 and 61001), so that
every router (MAVProxy, mavlink-router, ours) forwards them untouched: a router that
does not know the dialect passes an unknown message id as it is.  The messages are
packed with :mod:`struct`; the CRC extra of each is computed from the XML by
pymavlink's own parser (:mod:`pymavlink.generator.mavparse`), the standard way, so
the published XML and the bytes on air cannot drift apart.

``PQ_CHUNK`` (61000, 255-byte payload)::

    transfer u16 | index u8 | count u8 | len u8 | kind u8 | data[249]

A blob is cut into ``count`` (at most 32) chunks sharing the sender's ``transfer``
number.  ``kind`` says what the blob is: 1 HS1, 2 HS2, 3 a session frame in one chunk,
4 a session frame in several chunks, each of whose ``data[:len]`` ends with an 8-byte
**chunk MAC**: ``HMAC-SHA256(chunk key, sysid | compid | header | piece)[:8]``,
the chunk key derived from the sender's session data key.  Senders trim trailing
zero bytes (MAVLink v2); ``len`` says what is data.

Receiving (:class:`Reassembler`), cheap first: strict MAVLink parse and our CRC, the
header's bounds (``index < count <= 32``, ``len`` fits, a kind that needs one chunk
has one), then the chunk MAC for kind 4 under the keys of the live sessions, then its
transfer number against the newest one that opened from that sender under that key
(16-bit serial arithmetic: at or behind it, a recorded chunk, ``REPLAY_DETECTED``),
and only then the chunk is buffered.  A chunk flood without a session key therefore
cannot occupy the frame pool at all, nor can chunks replayed from the session's own
history; the handshake pool (HS1 from an unknown peer cannot carry a MAC) is separate
and small, and a full one evicts the transfer with the fewest chunks (the oldest among
equals), so a flood of first chunks cannot push out a handshake that is almost
complete, nor any command.  Transfers expire after ``timeout_s``; duplicates are
ignored, a conflicting chunk is refused; evictions, expiries and duplicates are counted
(:class:`ReassemblyStats`, exported by the link).  A lost chunk loses its blob; no
other blob can complete with it (the MAC binds each chunk to its transfer, index and
count; the session frame's tag binds everything again).  Transfer numbers are 16 bits:
a ground end rekeys after ``REKEY_TRANSFERS`` of them and stops sending in a session at
``TRANSFER_LIMIT``, so they never wrap within a session towards the vehicle; the
vehicle end's do wrap (it cannot rekey), so a chunk of its telemetry recorded more than
32,768 transfers ago can still take a slot of the ground end's pool until it expires
(its tag refuses it at the end).  An HS1 goes out under a random transfer number, so a
chunk planted ahead of it cannot spoil it; one injected in reaction to it (conflicting
count or piece) can, as jamming could; the ground end tries again after ``retry_s``.
Memory: ``(max_transfers + max_handshakes) * 32 * 249`` bytes at most.

Session frames travel **compact**, ``handle u8 | purpose u8 | counter u64 | inner |
tag``: magic, version and direction are implied, and the 16-byte session id is cut to
its last byte; the receiver rebuilds the full frame for each live session with that
handle (normally one) and the tag, computed over the full frame, decides (18 bytes
fewer per message, nothing less bound).  A session frame carries one plain MAVLink
message, the **inner**::

    src_sys u8 | src_comp u8 | seq u8 | msgid u24 LE | payload (as on the wire)

and the session frame's tag covers session id, direction, purpose, counter and the
inner, hence the message id, the source, and the target system/component (fields of
the payload; :func:`~antireplay.mavlink.codec.target`); the frame rebuilt from it is the
sender's frame, byte for byte (unsigned).  Choice of tag per message
(:data:`SIGNED_MESSAGES`): whatever changes what the vehicle does (commands, mode,
parameters, missions, guided setpoints, home and origin, file transfer, the serial
shell, log erasure) is a ``command`` frame, signed with the operator's ML-DSA-87 key
(non-repudiable, 4,627 bytes: 20 chunks), and the vehicle end refuses any of them in a
data frame (``SIGNATURE_REQUIRED``, before any cryptography); everything else (GCS
heartbeats, RC/manual control, and all telemetry from the vehicle) is a ``data`` frame
under the session's HMAC-SHA256-128 key (one chunk for messages up to 217 bytes of
payload: 38 bytes more on air than plain MAVLink, 25 more than MAVLink signing).

The two ends are sans-I/O here (:class:`GroundEnd`, :class:`VehicleEnd`); the
adapter that moves their bytes is :mod:`antireplay.mavlink.pq.link`.  Ground end:
starts a handshake at once and again (at most once per ``retry_s``) whenever the
session nears its counter limit (:attr:`~antireplay.pq.session.Session.needs_rekey`) or
its transfer limit, when nothing authenticated came from the vehicle for ``silence_s``
(a restarted vehicle end), or when the vehicle end reports it has no session
(``PQ_STATUS``, unauthenticated, so heeded only when nothing authenticated came from
the vehicle for ``retry_s``); while it has no session, queues at most ``max_queued``
commands, each for at most ``queue_ttl_s``, and drops the rest, every drop counted
(:attr:`GroundEnd.drops`); wraps every local message; unwraps telemetry.  Vehicle
end: answers HS1 with HS2 (:meth:`~antireplay.pq.session.Responder.accept_handshake`:
shape, freshness and the seen-set before the signature, commit after, so a replayed
HS1 opens nothing; it draws a session id whose handle no live session has), opens
frames with :meth:`~antireplay.pq.session.Responder.open` (window ``check`` before the
signature, ``commit`` after; for a handle two live sessions still share, under each
candidate in turn, so the tag decides and one session's window never refuses
another's frame), rebuilds the plain MAVLink frame for the flight controller, and
wraps the flight controller's telemetry under the newest session that authenticated.
The first frame that authenticates in a peer's new session closes that peer's older
sessions (:meth:`~antireplay.pq.session.Responder.close`), so a frame withheld from an
old session (jammed, recorded) can never be played later (``SESSION_CLOSED``); one
ground end per operator identity.  Every refusal is a typed error the caller counts.
Only MAVLink v2 travels: a v1 frame is refused on both sides (:class:`PlainFrameError`,
as plain MAVLink on the air is).
"""

from __future__ import annotations

import hmac
import secrets
import struct
from collections import Counter, OrderedDict, deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import IntEnum
from importlib import resources
from typing import Protocol

from cryptography.hazmat.primitives.asymmetric import mlkem, x25519
from pymavlink.dialects.v20 import ardupilotmega as dialect
from pymavlink.generator import mavparse
from pymavlink.generator.mavcrc import x25crc

from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import (
    InvalidFrameError,
    ReplayAttackError,
    ReplayDetectedError,
    SignatureInvalidError,
    SignatureRequiredError,
    UnknownSessionError,
)
from antireplay.mavlink.codec import HEADER, STX_V2, Frame, parse_frame
from antireplay.pq.session import (
    FRAME_MAGIC,
    VERSION,
    Direction,
    Initiator,
    Opened,
    Purpose,
    Responder,
    Session,
)

MSG_CHUNK, MSG_STATUS = 61000, 61001
CHUNK_DATA, CHUNK_MAC, MAX_CHUNKS = 249, 8, 32
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


def _load_dialect() -> dict[int, tuple[int, int]]:
    """``{msgid: (crc_extra, payload length)}`` from the published XML, by pymavlink."""
    xml = resources.files("antireplay.mavlink").joinpath("antireplay_pq.xml")
    with resources.as_file(xml) as path:
        parsed = mavparse.MAVXML(str(path), mavparse.PROTOCOL_2_0)
    return {m.id: (m.crc_extra, m.wire_length) for m in parsed.message}


DIALECT = _load_dialect()
DIALECT_XML = "antireplay_pq.xml"


class Kind(IntEnum):
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


@dataclass(frozen=True)
class Chunk:
    """One ``PQ_CHUNK``, bounds checked (not yet authenticated)."""

    sysid: int
    compid: int
    transfer: int
    index: int
    count: int
    kind: Kind
    data: bytes  # data[:len]: the piece, and for FRAME_CHUNKED its chunk MAC

    @property
    def key(self) -> tuple[int, int, int]:
        return self.sysid, self.compid, self.transfer

    @property
    def piece(self) -> bytes:
        return self.data[:-CHUNK_MAC] if self.kind is Kind.FRAME_CHUNKED else self.data

    def mac_input(self) -> bytes:
        head = _CHUNK.pack(self.transfer, self.index, self.count, len(self.data), self.kind)
        return bytes([self.sysid, self.compid]) + head + self.piece


_KINDS = {int(k): k for k in Kind}


class PlainFrameError(InvalidFrameError):
    """A plain MAVLink message (or a v1 frame) where only our dialect travels: on the air,
    routers' own heartbeats, known and benign, which an end counts rather than reports."""


def parse_chunk(frame: Frame) -> Chunk:
    """The cheap checks (module docstring); every failure is a typed INVALID_FRAME."""
    if frame.msgid not in DIALECT:
        raise PlainFrameError(f"plain MAVLink message {frame.msgid}, not carried")
    if frame.msgid != MSG_CHUNK:
        raise InvalidFrameError("not a PQ_CHUNK")
    payload = _payload_of(frame)
    transfer, index, count, length, kind = _CHUNK.unpack_from(payload)
    k = _KINDS.get(kind)
    if k is None:
        raise InvalidFrameError("unknown chunk kind")
    if not index < count <= MAX_CHUNKS:
        raise InvalidFrameError(f"chunk {index} of {count} (at most {MAX_CHUNKS})")
    if length > CHUNK_DATA or (k is Kind.FRAME_CHUNKED and length <= CHUNK_MAC):
        raise InvalidFrameError("chunk data length out of bounds")
    if k in (Kind.HS2, Kind.FRAME) and count != 1:
        raise InvalidFrameError(f"a {k.name} blob travels in one chunk")
    if k in (Kind.HS1, Kind.FRAME_CHUNKED) and count == 1:
        raise InvalidFrameError(f"a {k.name} blob travels in several chunks")
    data = payload[_CHUNK.size : _CHUNK.size + length]
    return Chunk(frame.sysid, frame.compid, transfer, index, count, k, data)


def chunk_key(data_key: bytes) -> bytes:
    """The chunk-MAC key of a session direction (derived from its data key)."""
    return hmac.digest(data_key, b"antireplay/v1 chunk", "sha256")


def _chunk_mac(key: bytes, chunk_input: bytes) -> bytes:
    return hmac.digest(key, chunk_input, "sha256")[:CHUNK_MAC]


@dataclass
class ChunkSender:
    """Cuts blobs into ``PQ_CHUNK`` frames from one MAVLink system/component."""

    sysid: int
    compid: int
    transfer: int = 0
    seq: int = 0

    def frames(
        self, blob: bytes, kind: Kind, mac_key: bytes | None = None, transfer: int | None = None
    ) -> list[bytes]:
        """``blob`` as chunk frames; a session frame needing several chunks gets chunk MACs.
        ``transfer``: this number instead of the next one (an HS1's unpredictable one)."""
        if kind is Kind.FRAME and len(blob) > CHUNK_DATA:
            kind = Kind.FRAME_CHUNKED
        room = CHUNK_DATA - (CHUNK_MAC if kind is Kind.FRAME_CHUNKED else 0)
        pieces = [blob[at : at + room] for at in range(0, len(blob), room)] or [b""]
        if len(pieces) > MAX_CHUNKS:
            raise ValueError(f"blob of {len(blob)} bytes needs more than {MAX_CHUNKS} chunks")
        if kind is Kind.FRAME_CHUNKED and mac_key is None:
            raise ValueError("a chunked session frame needs the chunk key")
        if transfer is None:
            self.transfer = transfer = (self.transfer + 1) & 0xFFFF
        out = []
        for index, piece in enumerate(pieces):
            data = piece
            if kind is Kind.FRAME_CHUNKED:
                assert mac_key is not None
                length = len(piece) + CHUNK_MAC
                head = _CHUNK.pack(transfer, index, len(pieces), length, kind)
                data += _chunk_mac(mac_key, bytes([self.sysid, self.compid]) + head + piece)
            payload = _CHUNK.pack(transfer, index, len(pieces), len(data), kind)
            payload += data.ljust(CHUNK_DATA, b"\0")
            out.append(self._pack(payload))
        return out

    def _pack(self, payload: bytes) -> bytes:
        self.seq += 1
        crc_extra = DIALECT[MSG_CHUNK][0]
        return pack_v2(
            MSG_CHUNK, payload, crc_extra, sysid=self.sysid, compid=self.compid, seq=self.seq
        )


@dataclass
class _Transfer:
    count: int
    kind: Kind
    started: float
    key: bytes | None
    pieces: dict[int, bytes] = field(default_factory=dict)


@dataclass
class ReassemblyStats:
    """What the reassembler threw away without an error to the caller."""

    duplicates: int = 0
    evicted: int = 0
    expired: int = 0


class Reassembler:
    """Bounded reassembly in two pools (module docstring); not thread-safe (one per end)."""

    def __init__(
        self,
        *,
        max_transfers: int = 4,
        max_handshakes: int = 2,
        timeout_s: float = 10.0,
        clock: Clock | None = None,
    ) -> None:
        self.max_transfers, self.max_handshakes = max_transfers, max_handshakes
        self.timeout_s = timeout_s
        self._clock = resolve(clock)
        self._frames: OrderedDict[tuple[int, int, int], _Transfer] = OrderedDict()
        self._handshakes: OrderedDict[tuple[int, int, int], _Transfer] = OrderedDict()
        # the newest transfer number that opened, per sender and chunk key (a few live keys)
        self._newest: OrderedDict[tuple[int, int, bytes], int] = OrderedDict()
        self.stats = ReassemblyStats()

    @property
    def buffered(self) -> int:
        """Bytes held for incomplete blobs."""
        pools = (self._frames, self._handshakes)
        return sum(len(p) for pool in pools for t in pool.values() for p in t.pieces.values())

    def feed(self, chunk: Chunk, keys: Iterable[bytes] = ()) -> tuple[Kind, bytes] | None:
        """Take one parsed chunk; the completed blob, or None; typed errors for bad chunks.

        ``keys`` are the chunk keys (:func:`chunk_key`) of the live sessions whose
        frames this end receives: a ``FRAME_CHUNKED`` chunk must carry a MAC under one.
        """
        if chunk.count == 1:
            return chunk.kind, chunk.piece
        self._expire()
        pool = self._handshakes if chunk.kind is Kind.HS1 else self._frames
        transfer = pool.get(chunk.key)
        key = self._authenticate(chunk, keys if transfer is None else (transfer.key,))
        if transfer is None:
            self._check_fresh(chunk, key)
            transfer = self._admit(pool, chunk, key)
        elif transfer.count != chunk.count or transfer.kind is not chunk.kind:
            raise InvalidFrameError("chunk disagrees with its transfer (count or kind)")
        known = transfer.pieces.get(chunk.index)
        if known is not None:
            if known != chunk.piece:
                raise InvalidFrameError("a different chunk for an index already held")
            self.stats.duplicates += 1
            return None
        transfer.pieces[chunk.index] = chunk.piece
        if len(transfer.pieces) < transfer.count:
            return None
        del pool[chunk.key]
        return transfer.kind, b"".join(transfer.pieces[i] for i in range(transfer.count))

    def opened(self, chunk: Chunk, key: bytes) -> None:
        """The blob ``chunk`` belongs to opened (authenticated, fresh) in the session whose
        chunk key is ``key``: chunks of this transfer and earlier ones (16-bit serial
        arithmetic) from that sender are replays from now on."""
        at = (chunk.sysid, chunk.compid, key)
        newest = self._newest.get(at)
        if newest is None or 0 < (chunk.transfer - newest) & 0xFFFF < 0x8000:
            self._newest[at] = chunk.transfer
            self._newest.move_to_end(at)
            if len(self._newest) > MAX_SENDER_KEYS:
                self._newest.popitem(last=False)

    def _check_fresh(self, chunk: Chunk, key: bytes | None) -> None:
        newest = None if key is None else self._newest.get((chunk.sysid, chunk.compid, key))
        if newest is not None and (newest - chunk.transfer) & 0xFFFF < 0x8000:
            raise ReplayDetectedError(
                f"chunk of transfer {chunk.transfer}, at or before {newest} that opened"
            )

    def _authenticate(self, chunk: Chunk, keys: Iterable[bytes | None]) -> bytes | None:
        if chunk.kind is not Kind.FRAME_CHUNKED:
            return None
        mac, data = chunk.data[-CHUNK_MAC:], chunk.mac_input()
        for key in keys:
            if key is not None and hmac.compare_digest(_chunk_mac(key, data), mac):
                return key
        raise SignatureInvalidError("chunk MAC does not verify under any live session")

    def _admit(
        self, pool: OrderedDict[tuple[int, int, int], _Transfer], chunk: Chunk, key: bytes | None
    ) -> _Transfer:
        limit = self.max_handshakes if pool is self._handshakes else self.max_transfers
        if len(pool) >= limit:
            victim = min(pool, key=lambda k: len(pool[k].pieces))  # fewest chunks, oldest first
            del pool[victim]
            self.stats.evicted += 1
        transfer = _Transfer(chunk.count, chunk.kind, self._clock.monotonic(), key)
        pool[chunk.key] = transfer
        return transfer

    def _expire(self) -> None:
        horizon = self._clock.monotonic() - self.timeout_s
        for pool in (self._frames, self._handshakes):
            for key in [k for k, t in pool.items() if t.started < horizon]:
                del pool[key]
                self.stats.expired += 1


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


class Receiver(Protocol):
    """What opens session frames: a :class:`~antireplay.pq.session.Session` or a
    :class:`~antireplay.pq.session.Responder` (``check`` records nothing, ``open`` commits)."""

    def check(self, frame: bytes) -> None: ...

    def open(self, frame: bytes) -> Opened: ...


def open_compact(
    air: bytes, sessions: Iterable[Session], direction: Direction, receiver: Receiver
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


@dataclass
class Output:
    """What an end wants written: plain frames for its local side, chunks for the air."""

    local: list[bytes] = field(default_factory=list)
    air: list[bytes] = field(default_factory=list)
    #: A blob verified (HS1, HS2, a session frame): its sender may be learned as the air peer.
    authenticated: bool = False


def _parse(raw: bytes) -> Frame:
    frame = parse_frame(raw)
    if frame.version != 2:
        raise PlainFrameError("MAVLink v1 frames are not carried")
    return frame


class GroundEnd:
    """The initiator's end, next to the ground station (module docstring)."""

    def __init__(
        self,
        initiator: Initiator,
        responder_key: mlkem.MLKEM1024PublicKey,
        *,
        system_id: int = 255,
        component_id: int = 197,
        signed: frozenset[int] = SIGNED_MESSAGES,
        retry_s: float = 2.0,
        silence_s: float = 5.0,
        max_queued: int = 8,
        queue_ttl_s: float = 5.0,
        hybrid: x25519.X25519PublicKey | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.initiator, self.responder_key = initiator, responder_key
        self.hybrid = hybrid  # the vehicle's static X25519 key: hybrid handshakes
        self.signed = signed
        self.retry_s, self.silence_s = retry_s, silence_s
        self.sender = ChunkSender(system_id, component_id)
        self._first_transfer = 0  # the sender's transfer number when the session began
        self.session: Session | None = None
        self._clock = resolve(clock)
        self._reassembler = Reassembler(clock=clock)
        self._pending: tuple[bytes, float] | None = None  # HS1 and when it left
        self.max_queued, self.queue_ttl_s = max_queued, queue_ttl_s
        self._queue: deque[tuple[bytes, float]] = deque()  # commands and when they came
        self._heard = float("-inf")  # when an authenticated frame last came from the vehicle
        #: Local messages that never left, by reason: ``NO_SESSION`` (not a command, no
        #: session), ``QUEUE_FULL`` (the oldest queued command, pushed out by a newer one),
        #: ``QUEUE_EXPIRED`` (a command that waited longer than ``queue_ttl_s``).
        self.drops: Counter[str] = Counter()

    def handshake(self) -> list[bytes]:
        """Start a new handshake (the current session keeps working until HS2 arrives).  Its
        transfer number is random: nobody can plant a conflicting chunk ahead of it."""
        hs1 = self.initiator.start(self.responder_key, self.hybrid)
        self._pending = (hs1, self._clock.monotonic())
        return self.sender.frames(hs1, Kind.HS1, transfer=secrets.randbelow(0x10000))

    def from_local(self, raw: bytes) -> list[bytes]:
        """Wrap one plain frame from a local peer.  While there is no session, commands wait
        in a bounded queue, each at most ``queue_ttl_s`` (a command is meant for now, not
        for whenever the link comes back), and the rest is dropped: a heartbeat comes
        again, and must not push a command out of the queue.  Every drop is counted in
        :attr:`drops`."""
        frame = _parse(raw)
        if self.session is not None and self._transfers_used() >= TRANSFER_LIMIT:
            self.session = None  # its transfer numbers would wrap: wait for the new one
        if self.session is None:
            if frame.msgid in self.signed:
                self._expire_queue()
                if len(self._queue) >= self.max_queued:
                    self._queue.popleft()
                    self.drops["QUEUE_FULL"] += 1
                self._queue.append((raw, self._clock.monotonic()))
            else:
                self.drops["NO_SESSION"] += 1
            return self._retry()
        purpose = Purpose.COMMAND if frame.msgid in self.signed else Purpose.DATA
        return self._seal(self.session, inner_of(frame), purpose) + self._renew(self.session)

    def _renew(self, session: Session) -> list[bytes]:
        """A new handshake (rate-limited by ``retry_s``) when this session should end: its
        counters near their limit, its chunks' transfer numbers near half their range
        (:data:`REKEY_TRANSFERS`), or nothing authenticated came from the vehicle for
        ``silence_s`` (a restarted vehicle end; its ``PQ_STATUS`` hint can be lost or
        outrun by an attacker's junk)."""
        silent = self._clock.monotonic() - self._heard >= self.silence_s
        if session.needs_rekey or silent or self._transfers_used() >= REKEY_TRANSFERS:
            return self._retry()
        return []

    def _transfers_used(self) -> int:
        return (self.sender.transfer - self._first_transfer) & 0xFFFF

    def _seal(self, session: Session, inner: bytes, purpose: Purpose) -> list[bytes]:
        blob = compact(session.seal(inner, purpose))
        return self.sender.frames(blob, Kind.FRAME, chunk_key(session.send_key))

    def _retry(self) -> list[bytes]:
        if self._pending is not None and self._clock.monotonic() - self._pending[1] < self.retry_s:
            return []
        return self.handshake()

    def from_air(self, raw: bytes) -> Output:
        """One frame from the air: HS2, telemetry, or the vehicle end's hint."""
        frame = _parse(raw)
        if frame.msgid == MSG_STATUS:  # unauthenticated: heeded only when the vehicle is silent
            silent = self._clock.monotonic() - self._heard >= self.retry_s
            hinted = read_status(frame) == STATUS_NO_SESSION and silent
            return Output(air=self._retry() if hinted else [])
        keys = [chunk_key(self.session.recv_key)] if self.session is not None else []
        chunk = parse_chunk(frame)
        done = self._reassembler.feed(chunk, keys)
        if done is None:
            return Output()
        kind, blob = done
        if kind is Kind.HS2:
            return self._finish(blob)
        if kind not in (Kind.FRAME, Kind.FRAME_CHUNKED) or self.session is None:
            raise UnknownSessionError(f"{kind.name} blob with no session to take it")
        opened = open_compact(blob, [self.session], Direction.R2I, self.session)
        self._reassembler.opened(chunk, keys[0])
        self._heard = self._clock.monotonic()
        return Output(local=[plain_frame(opened.payload)], authenticated=True)

    def _finish(self, hs2: bytes) -> Output:
        if self._pending is None:
            raise UnknownSessionError("HS2 with no handshake in progress")
        self.session = self.initiator.finish(self._pending[0], hs2)
        self._pending, self._heard = None, self._clock.monotonic()
        self._first_transfer = self.sender.transfer
        out = Output(authenticated=True)
        self._expire_queue()
        while self._queue:
            out.air += self.from_local(self._queue.popleft()[0])
        return out

    def _expire_queue(self) -> None:
        horizon = self._clock.monotonic() - self.queue_ttl_s
        while self._queue and self._queue[0][1] < horizon:
            self._queue.popleft()
            self.drops["QUEUE_EXPIRED"] += 1

    @property
    def unsent(self) -> int:
        """Local messages that never left (:attr:`drops`, all reasons)."""
        return sum(self.drops.values())

    @property
    def reassembly(self) -> ReassemblyStats:
        return self._reassembler.stats


class VehicleEnd:
    """The responder's end, next to the autopilot (module docstring)."""

    def __init__(
        self,
        responder: Responder,
        *,
        system_id: int = 1,
        component_id: int = 197,
        hint_interval_s: float = 1.0,
        signed: frozenset[int] = SIGNED_MESSAGES,
        clock: Clock | None = None,
    ) -> None:
        self.responder = responder
        self.signed = signed  # messages delivered only from a command (ML-DSA-87) frame
        self.sender = ChunkSender(system_id, component_id)
        self.hint_interval_s = hint_interval_s
        self._clock = resolve(clock)
        self._reassembler = Reassembler(clock=clock)
        self._sessions: deque[Session] = deque(maxlen=responder.max_sessions)
        self.current: Session | None = None  # the newest session that authenticated
        self._hinted = float("-inf")

    def from_air(self, raw: bytes) -> Output:
        """One frame from the air: HS1 (answered with HS2) or a session frame for the FC."""
        frame = _parse(raw)
        keys = [chunk_key(s.recv_key) for s in self._sessions]
        try:
            chunk = parse_chunk(frame)
            done = self._reassembler.feed(chunk, keys)
        except SignatureInvalidError:
            if keys:
                raise
            raise UnknownSessionError("a session frame, and no live session here") from None
        if done is None:
            return Output()
        kind, blob = done
        if kind is Kind.HS1:
            handles = {s.session_id[-1] for s in self._sessions}
            session, hs2 = self.responder.accept_handshake(blob, lambda sid: sid[-1] in handles)
            self._sessions.append(session)
            self.current = session
            return Output(air=self.sender.frames(hs2, Kind.HS2), authenticated=True)
        if kind is Kind.HS2:
            raise InvalidFrameError("HS2 travels to the ground end")
        self._require_signature(blob)
        opened = open_compact(blob, self._sessions, Direction.I2R, self.responder)
        session = next(s for s in self._sessions if s.session_id == opened.session_id)
        self._reassembler.opened(chunk, chunk_key(session.recv_key))
        self._supersede(session)
        self.current = session
        return Output(local=[plain_frame(opened.payload)], authenticated=True)

    def _require_signature(self, air: bytes) -> None:
        """Refuse, before any cryptography, a message that must be signed (:attr:`signed`)
        but travels in a data frame: a holder of the session's HMAC keys (a ground end
        configured otherwise, or an insider) cannot command the vehicle."""
        inner_at = _COMPACT.size
        if len(air) < inner_at + _INNER_HEAD:
            raise InvalidFrameError("session frame too short")
        msgid = int.from_bytes(air[inner_at + 3 : inner_at + 6], "little")
        if air[1] != Purpose.COMMAND and msgid in self.signed:
            raise SignatureRequiredError(f"message {msgid} must be signed (ML-DSA-87)")

    def _supersede(self, session: Session) -> None:
        """Close the peer's older sessions once a newer one carried a frame: the ground end
        has moved on, so a frame withheld from an old session can never be played later."""
        for old in [s for s in self._sessions if s.peer_id == session.peer_id]:
            if old.seq < session.seq:
                self.responder.close(old)
                self._sessions.remove(old)

    def hint(self) -> list[bytes]:
        """A rate-limited ``PQ_STATUS`` telling the ground end it has no session here."""
        now = self._clock.monotonic()
        if now - self._hinted < self.hint_interval_s:
            return []
        self._hinted = now
        return [status_frame(STATUS_NO_SESSION, self.sender.sysid, self.sender.compid)]

    def from_local(self, raw: bytes) -> list[bytes]:
        """Wrap one telemetry frame from the flight controller (dropped with no session)."""
        frame = _parse(raw)
        if self.current is None:
            raise UnknownSessionError("no session to carry telemetry yet")
        blob = compact(self.current.seal(inner_of(frame), Purpose.DATA))
        return self.sender.frames(blob, Kind.FRAME, chunk_key(self.current.send_key))

    @property
    def reassembly(self) -> ReassemblyStats:
        return self._reassembler.stats


__all__ = [
    "CHUNK_DATA",
    "DIALECT",
    "MSG_CHUNK",
    "MSG_STATUS",
    "SIGNED_MESSAGES",
    "Chunk",
    "ChunkSender",
    "GroundEnd",
    "Kind",
    "Output",
    "PlainFrameError",
    "Reassembler",
    "ReassemblyStats",
    "VehicleEnd",
    "chunk_key",
    "inner_of",
    "parse_chunk",
    "plain_frame",
]
