"""Chunks: a session frame cut into MAVLink-sized pieces, each MACed, and reassembled.

See :mod:`antireplay.mavlink.pq` for the reassembly rules.
"""

from __future__ import annotations

import hmac
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass, field

from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import (
    InvalidFrameError,
    ReplayDetectedError,
    SignatureInvalidError,
)
from antireplay.mavlink.codec import Frame
from antireplay.mavlink.pq.wire import (
    _CHUNK,
    CHUNK_DATA,
    CHUNK_MAC,
    DIALECT,
    MAX_CHUNKS,
    MAX_SENDER_KEYS,
    MSG_CHUNK,
    ChunkKind,
    _payload_of,
    pack_v2,
)


@dataclass(frozen=True)
class Chunk:
    """One ``PQ_CHUNK``, bounds checked (not yet authenticated)."""

    sysid: int
    compid: int
    transfer: int
    index: int
    count: int
    kind: ChunkKind
    data: bytes  # data[:len]: the piece, and for FRAME_CHUNKED its chunk MAC

    @property
    def key(self) -> tuple[int, int, int]:
        return self.sysid, self.compid, self.transfer

    @property
    def piece(self) -> bytes:
        return self.data[:-CHUNK_MAC] if self.kind is ChunkKind.FRAME_CHUNKED else self.data

    def mac_input(self) -> bytes:
        head = _CHUNK.pack(self.transfer, self.index, self.count, len(self.data), self.kind)
        return bytes([self.sysid, self.compid]) + head + self.piece


_KINDS = {int(k): k for k in ChunkKind}


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
    if length > CHUNK_DATA or (k is ChunkKind.FRAME_CHUNKED and length <= CHUNK_MAC):
        raise InvalidFrameError("chunk data length out of bounds")
    if k in (ChunkKind.HS2, ChunkKind.FRAME) and count != 1:
        raise InvalidFrameError(f"a {k.name} blob travels in one chunk")
    if k in (ChunkKind.HS1, ChunkKind.FRAME_CHUNKED) and count == 1:
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
        self,
        blob: bytes,
        kind: ChunkKind,
        mac_key: bytes | None = None,
        transfer: int | None = None,
    ) -> list[bytes]:
        """``blob`` as chunk frames; a session frame needing several chunks gets chunk MACs.
        ``transfer``: this number instead of the next one (an HS1's unpredictable one)."""
        if kind is ChunkKind.FRAME and len(blob) > CHUNK_DATA:
            kind = ChunkKind.FRAME_CHUNKED
        room = CHUNK_DATA - (CHUNK_MAC if kind is ChunkKind.FRAME_CHUNKED else 0)
        pieces = [blob[at : at + room] for at in range(0, len(blob), room)] or [b""]
        if len(pieces) > MAX_CHUNKS:
            raise ValueError(f"blob of {len(blob)} bytes needs more than {MAX_CHUNKS} chunks")
        if kind is ChunkKind.FRAME_CHUNKED and mac_key is None:
            raise ValueError("a chunked session frame needs the chunk key")
        if transfer is None:
            self.transfer = transfer = (self.transfer + 1) & 0xFFFF
        out = []
        for index, piece in enumerate(pieces):
            data = piece
            if kind is ChunkKind.FRAME_CHUNKED:
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
    kind: ChunkKind
    started: float
    key: bytes | None
    pieces: dict[int, bytes] = field(default_factory=dict)


@dataclass
class ReassemblyStats:
    """What the reassembler threw away without an error to the caller, and the blobs it
    completed (``reassembled``: each handed on, to be opened or refused)."""

    reassembled: int = 0
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

    def feed(self, chunk: Chunk, keys: Iterable[bytes] = ()) -> tuple[ChunkKind, bytes] | None:
        """Take one parsed chunk; the completed blob, or None; typed errors for bad chunks.

        ``keys`` are the chunk keys (:func:`chunk_key`) of the live sessions whose
        frames this end receives: a ``FRAME_CHUNKED`` chunk must carry a MAC under one.
        """
        if chunk.count == 1:
            self.stats.reassembled += 1
            return chunk.kind, chunk.piece
        self._expire()
        pool = self._handshakes if chunk.kind is ChunkKind.HS1 else self._frames
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
        self.stats.reassembled += 1
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
        if chunk.kind is not ChunkKind.FRAME_CHUNKED:
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
