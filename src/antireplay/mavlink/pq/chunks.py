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
    MAX_PARITY,
    MAX_SENDER_KEYS,
    MSG_CHUNK,
    ChunkKind,
    _payload_of,
    pack_v2,
    parity_for,
)

#: Repair requests a receiver sends for one transfer, at most (each after a silence).
MAX_NACKS = 8


@dataclass(frozen=True)
class Chunk:
    """One ``PQ_CHUNK``, bounds checked (not yet authenticated)."""

    sysid: int
    compid: int
    transfer: int
    index: int
    count: int
    kind: ChunkKind
    data: bytes  # data[:len] (a parity chunk: all of it): the piece, and for FRAME_CHUNKED its MAC
    parity: int = 0  # parity chunks after the ``count`` data chunks
    tail: int = 0  # a parity chunk's ``len``: the last data chunk's

    @property
    def key(self) -> tuple[int, int, int]:
        return self.sysid, self.compid, self.transfer

    @property
    def is_parity(self) -> bool:
        return self.index >= self.count

    @property
    def total(self) -> int:
        """Data and parity chunks of the blob."""
        return self.count + self.parity

    @property
    def piece(self) -> bytes:
        return self.data[:-CHUNK_MAC] if self.kind is ChunkKind.FRAME_CHUNKED else self.data

    @property
    def header(self) -> bytes:
        """The chunk header as it travels (``len`` a parity chunk's: the last data chunk's)."""
        length = self.tail if self.is_parity else len(self.data)
        kind = self.kind | self.parity << 4
        return _CHUNK.pack(self.transfer, self.index, self.count, length, kind)

    def mac_input(self) -> bytes:
        return bytes([self.sysid, self.compid]) + self.header + self.piece


def _room(kind: ChunkKind) -> int:
    """Bytes of blob per chunk of this kind (a chunk MAC takes the rest)."""
    return CHUNK_DATA - (CHUNK_MAC if kind is ChunkKind.FRAME_CHUNKED else 0)


def _xor(pieces: Iterable[bytes], room: int) -> bytes:
    """The XOR of ``pieces``, each zero-padded to ``room`` bytes."""
    out = 0
    for piece in pieces:
        out ^= int.from_bytes(piece.ljust(room, b"\0"), "big")
    return out.to_bytes(room, "big")


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
    transfer, index, count, length, kind_byte = _CHUNK.unpack_from(payload)
    k, parity = _KINDS.get(kind_byte & 0x0F), kind_byte >> 4
    if k is None:
        raise InvalidFrameError("unknown chunk kind")
    if not 0 < count <= MAX_CHUNKS or parity > MAX_PARITY or index >= count + parity:
        raise InvalidFrameError(
            f"chunk {index} of {count} and {parity} parity (at most {MAX_CHUNKS} and {MAX_PARITY})"
        )
    if length > CHUNK_DATA or (k is ChunkKind.FRAME_CHUNKED and length <= CHUNK_MAC):
        raise InvalidFrameError("chunk data length out of bounds")
    if k in (ChunkKind.HS2, ChunkKind.FRAME) and (count != 1 or parity):
        raise InvalidFrameError(f"a {k.name} blob travels in one chunk")
    if k in (ChunkKind.HS1, ChunkKind.FRAME_CHUNKED) and count == 1:
        raise InvalidFrameError(f"a {k.name} blob travels in several chunks")
    at = _CHUNK.size
    if index >= count:  # parity: all data in use, len the last data chunk's
        ids = frame.sysid, frame.compid
        return Chunk(*ids, transfer, index, count, k, payload[at:], parity, length)
    if parity and index < count - 1 and length != CHUNK_DATA:
        raise InvalidFrameError("only the last data chunk of a blob with parity is short")
    data = payload[at : at + length]
    return Chunk(frame.sysid, frame.compid, transfer, index, count, k, data, parity)


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
        """``blob`` as chunk frames, data then parity (:func:`parity_for`); a session frame
        needing several chunks gets chunk MACs, parity chunks too.  ``transfer``: this
        number instead of the next one (an HS1's unpredictable one)."""
        if kind is ChunkKind.FRAME and len(blob) > CHUNK_DATA:
            kind = ChunkKind.FRAME_CHUNKED
        room = _room(kind)
        pieces = [blob[at : at + room] for at in range(0, len(blob), room)] or [b""]
        if len(pieces) > MAX_CHUNKS:
            raise ValueError(f"blob of {len(blob)} bytes needs more than {MAX_CHUNKS} chunks")
        if kind is ChunkKind.FRAME_CHUNKED and mac_key is None:
            raise ValueError("a chunked session frame needs the chunk key")
        if transfer is None:
            self.transfer = transfer = (self.transfer + 1) & 0xFFFF
        count, parity = len(pieces), parity_for(len(pieces))
        mac = CHUNK_MAC if kind is ChunkKind.FRAME_CHUNKED else 0
        tail = len(pieces[-1]) + mac
        groups = [_xor(pieces[j::parity], room) for j in range(parity)]
        out = []
        for index, piece in enumerate(pieces + groups):
            data = piece + bytes(mac)  # the MAC's room, filled below
            ids = self.sysid, self.compid, transfer, index, count, kind
            chunk = Chunk(*ids, data, parity, tail)
            if mac:
                assert mac_key is not None
                data = piece + _chunk_mac(mac_key, chunk.mac_input())
            out.append(self._pack(chunk.header + data.ljust(CHUNK_DATA, b"\0")))
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
    parity: int
    kind: ChunkKind
    started: float
    key: bytes | None
    seen: float  # when a chunk of it (or a repair request for it) last came or went
    pieces: dict[int, bytes] = field(default_factory=dict)  # data and parity, by index
    tail: int | None = None  # the last data chunk's len, once known
    nacks: int = 0

    def missing(self) -> list[int]:
        """The fewest chunk indices that would complete the blob: in each parity group,
        its missing data chunks less one when its parity chunk is held."""
        if self.parity == 0:
            return [i for i in range(self.count) if i not in self.pieces]
        out = []
        for j in range(self.parity):
            lost = [i for i in range(j, self.count, self.parity) if i not in self.pieces]
            out += lost[1:] if self.count + j in self.pieces else lost
        return out

    def blob(self) -> bytes | None:
        """The blob, rebuilding one lost data chunk per group from its parity; or None."""
        if self.missing():
            return None
        room = _room(self.kind)
        pieces = dict(self.pieces)
        for j in range(self.parity):
            group = range(j, self.count, self.parity)
            lost = [i for i in group if i not in pieces]
            if lost:
                known = [pieces[i] for i in group if i in pieces]
                piece = _xor([pieces[self.count + j], *known], room)
                if lost[0] == self.count - 1:
                    assert self.tail is not None
                    piece = piece[: self.tail - (CHUNK_DATA - room)]
                pieces[lost[0]] = piece
        return b"".join(pieces[i] for i in range(self.count))


@dataclass
class ReassemblyStats:
    """What the reassembler threw away without an error to the caller, and the blobs it
    completed (``reassembled``: each handed on, to be opened or refused); ``rebuilt``:
    blobs that needed a parity chunk; ``late``: chunks of a blob already complete that
    were not needed (parity after a whole blob, repairs that crossed)."""

    reassembled: int = 0
    duplicates: int = 0
    evicted: int = 0
    expired: int = 0
    rebuilt: int = 0
    late: int = 0


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
        self.handshake_timeout_s = timeout_s  # an HS1's, stretched on slow radios (.wire)
        self._clock = resolve(clock)
        self._frames: OrderedDict[tuple[int, int, int], _Transfer] = OrderedDict()
        self._handshakes: OrderedDict[tuple[int, int, int], _Transfer] = OrderedDict()
        # the newest transfer number that opened, per sender and chunk key (a few live keys)
        self._newest: OrderedDict[tuple[int, int, bytes], int] = OrderedDict()
        # blobs completed lately: the chunk indices that came (late ones are not replays)
        self._done: OrderedDict[tuple[int, int, int], set[int]] = OrderedDict()
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
            came = self._done.get(chunk.key)
            if came is not None and chunk.index not in came:  # not needed, and no replay
                came.add(chunk.index)
                self.stats.late += 1
                return None
            self._check_fresh(chunk, key)
            transfer = self._admit(pool, chunk, key)
        elif (transfer.count, transfer.parity, transfer.kind) != (
            chunk.count,
            chunk.parity,
            chunk.kind,
        ):
            raise InvalidFrameError("chunk disagrees with its transfer (count, parity or kind)")
        self._take(transfer, chunk)
        blob = transfer.blob()
        if blob is None:
            return None
        del pool[chunk.key]
        self._done[chunk.key] = set(transfer.pieces)
        if len(self._done) > 2 * (self.max_transfers + self.max_handshakes):
            self._done.popitem(last=False)
        self.stats.reassembled += 1
        self.stats.rebuilt += any(i not in transfer.pieces for i in range(transfer.count))
        return transfer.kind, blob

    def _take(self, transfer: _Transfer, chunk: Chunk) -> None:
        tail = chunk.tail if chunk.is_parity else len(chunk.data)
        if chunk.is_parity or chunk.index == chunk.count - 1:
            if transfer.tail not in (None, tail):
                raise InvalidFrameError("chunk disagrees with its transfer (last length)")
            transfer.tail = tail
        known = transfer.pieces.get(chunk.index)
        if known is not None:
            if known != chunk.piece:
                raise InvalidFrameError("a different chunk for an index already held")
            self.stats.duplicates += 1
            return
        transfer.pieces[chunk.index] = chunk.piece
        transfer.seen = self._clock.monotonic()

    def missing(self, chunk: Chunk) -> list[int] | None:
        """The indices ``chunk``'s blob still needs when ``chunk`` was the last of its
        transfer on the air (its highest index): a repair is due now; else None."""
        pool = self._handshakes if chunk.kind is ChunkKind.HS1 else self._frames
        transfer = pool.get(chunk.key)
        if transfer is None or chunk.index != chunk.total - 1:
            return None
        return transfer.missing()

    def lookup(
        self, sender: tuple[int, int], number: int
    ) -> tuple[ChunkKind, bytes | None, list[int]] | None:
        """An incomplete transfer from ``sender``: its kind, chunk key and missing indices."""
        for pool in (self._frames, self._handshakes):
            transfer = pool.get((*sender, number))
            if transfer is not None:
                return transfer.kind, transfer.key, transfer.missing()
        return None

    def completed(self, sender: tuple[int, int], number: int) -> bool:
        """Whether that transfer completed lately (its blob was handed on)."""
        return (*sender, number) in self._done

    def stale(
        self, gap_s: float
    ) -> list[tuple[tuple[int, int, int], ChunkKind, bytes | None, list[int]]]:
        """Incomplete transfers nothing came or went for in ``gap_s`` (their tail or a
        repair lost), each at most ``MAX_NACKS`` times: (key, kind, chunk key, missing).
        Each one returned counts as asked again (:meth:`asked`)."""
        now = self._clock.monotonic()
        out = []
        for pool in (self._frames, self._handshakes):
            for key, t in pool.items():
                if now - t.seen >= gap_s and t.nacks < MAX_NACKS:
                    out.append((key, t.kind, t.key, t.missing()))
        for key, *_ in out:
            self.asked(key)
        return out

    def asked(self, key: tuple[int, int, int]) -> bool:
        """A repair request went out for transfer ``key``: its timer restarts.  False when
        its budget is spent (the caller sends none)."""
        for pool in (self._frames, self._handshakes):
            transfer = pool.get(key)
            if transfer is not None:
                transfer.seen = self._clock.monotonic()
                transfer.nacks += 1
                return transfer.nacks <= MAX_NACKS
        return False

    def opened(self, chunk: Chunk, key: bytes) -> None:
        """The blob ``chunk`` belongs to opened (authenticated, fresh) in the session whose
        chunk key is ``key``: chunks of this transfer and earlier ones (16-bit serial
        arithmetic) from that sender are replays from now on.  A one-chunk blob marks
        nothing: it never sat in the pool (its replay is the session window's to refuse),
        and a pacer sends it ahead of the chunks of an earlier transfer, which must not
        then look replayed."""
        if chunk.count == 1:
            return
        at = (chunk.sysid, chunk.compid, key)
        newest = self._newest.get(at)
        if newest is None or 0 < (chunk.transfer - newest) & 0xFFFF < 0x8000:
            self._newest[at] = chunk.transfer
            self._newest.move_to_end(at)
            if len(self._newest) > MAX_SENDER_KEYS:
                self._newest.popitem(last=False)

    def is_fresh(self, sender: tuple[int, int], number: int, key: bytes) -> bool:
        """Whether a transfer with this number could still open (after the newest that did)."""
        newest = self._newest.get((*sender, key))
        return newest is None or not (newest - number) & 0xFFFF < 0x8000

    def _check_fresh(self, chunk: Chunk, key: bytes | None) -> None:
        if key is not None and not self.is_fresh((chunk.sysid, chunk.compid), chunk.transfer, key):
            raise ReplayDetectedError(
                f"chunk of transfer {chunk.transfer}, at or before the newest that opened"
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
        now = self._clock.monotonic()
        transfer = _Transfer(chunk.count, chunk.parity, chunk.kind, now, key, now)
        pool[chunk.key] = transfer
        return transfer

    def _expire(self) -> None:
        now = self._clock.monotonic()
        for pool, timeout in (
            (self._frames, self.timeout_s),
            (self._handshakes, self.handshake_timeout_s),
        ):
            horizon = now - timeout
            for key in [k for k, t in pool.items() if t.started < horizon]:
                del pool[key]
                self.stats.expired += 1
