"""MAVLink v2 signing guard, sender helper and UDP proxy (pymavlink's gaps closed).

Theory of operation
-------------------
A signed MAVLink v2 frame ends with a 13-byte trailer: ``link_id`` (1 byte), a
48-bit timestamp (10 µs units since 2015-01-01 UTC, little-endian) and the
first 6 bytes of ``SHA-256(key | frame without those 6 bytes)``.
:meth:`MavlinkGuard.check` judges one frame, in this order:

1. **parse** strictly (v2 only, known incompat flags, exact length, CRC with
   the dialect's ``crc_extra`` when the message is known) -> ``INVALID_FRAME``;
2. **direction**: a frame whose *source* system is in ``refused_sources`` is
   refused with ``WRONG_DIRECTION`` (see *Direction binding* below); a
   guard built with ``system_id`` refuses that id as a source from the start;
   **unsigned** frames pass only if their message id is on the explicit
   allow-list; a frame carrying the signed flag never falls back to it;
3. **verify** the signature in constant time -> ``SIGNATURE_INVALID``.  Nothing
   before this point touches the stream table, so a forged frame with
   timestamp ``2**48 - 1`` changes nothing (pymavlink records it first and is
   jammed until restart), and forged frames cannot grow the table;
4. **bind** to this vehicle: with ``system_id`` set, a frame whose
   ``target_system`` is another vehicle is refused (0 = broadcast passes);
5. **timestamp rules** per stream ``(system, component, link)``:
   a known stream needs ``ts > last`` (or, with ``reorder_window``, a fresh
   counter in an RFC 6479 :class:`~antireplay.counters.CounterWindow`);
   a *new* stream's first timestamp must be within ``new_stream_max_age_s``
   (60 s) of the **receiver's wall clock** (pymavlink compares it with its own
   counter, which a restart resets) and above the eviction fence; any
   timestamp more than ``max_forward_s`` ahead of the wall clock is refused;
6. **commit** under a lock: the stream's state advances; with a store the
   timestamp is written through (``advance``) *before* the frame is
   forwarded, so a restarted guard on the same SQLite file or Redis rejects
   every capture it had accepted (the spec asks for "at least once a minute";
   write-through closes even that minute).

The stream table is bounded: when full, the least recently used stream is
evicted and a fence rises to its last timestamp; new streams must be above it.

Direction binding
-----------------
Both directions of a link share one key: ground stations (MAVProxy, QGC,
pymavlink's ``setup_signing``) sign and verify with a single secret per link,
so separate keys per direction would break every stock ground station.  The
``link_id`` cannot carry the direction either: each sender picks its own
(QGC uses its link number), so the proxy cannot pin it.  What does separate
the directions is the **source system id** in the frame header, which the
signature covers: the vehicle (and its components) send as the vehicle's
system id, a ground station as its own (255 by default), and MAVLink requires
them to differ on one network.  So a guard refuses, before any crypto, frames
whose source system belongs to the other side: the vehicle's own id
(``system_id``, when configured) and, in :class:`MavlinkProxy`, every source
system id that has *authenticated* in the other direction (learned only from
signed, accepted frames; an unsigned allow-listed frame teaches nothing, or a
spoofed unsigned heartbeat could silence the real vehicle).  A signed vehicle
frame reflected back to the listen port therefore gets ``WRONG_DIRECTION``,
and stamps nothing in the inbound stream table.  Configure ``--system-id``:
without it, a reflection is refused only once the vehicle has spoken through
this proxy process.

Sender side: :class:`TimestampSource` keeps a link's timestamp tied to real
time (``max(last + 1, now)``) and raises :class:`NonceExhaustedError` at
``2**48`` instead of truncating; :func:`sign_frame` signs a v2 frame with it.
"""

from __future__ import annotations

import hashlib
import hmac
import socket
import struct
import threading
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as dialect
from pymavlink.generator.mavcrc import x25crc

from antireplay.clock import Clock, resolve
from antireplay.counters import CounterWindow
from antireplay.errors import (
    AuthenticationError,
    CounterReplayError,
    InvalidFrameError,
    MessageFromFutureError,
    MessageStaleError,
    NonceExhaustedError,
    ReplayAttackError,
    WrongDirectionError,
)
from antireplay.stores import ReplayStore

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


@dataclass(frozen=True)
class MavVerdict:
    """An accepted frame."""

    stream: tuple[int, int, int]
    msgid: int
    timestamp: int
    signed: bool


@dataclass
class _Stream:
    last: int
    floor: int = -1  # restored from a store: everything at or below was (or may have been) seen
    window: CounterWindow | None = None


class MavlinkGuard:
    """Judges MAVLink v2 frames: verify, bind, timestamp rules, commit (module docstring)."""

    def __init__(
        self,
        key: bytes,
        *,
        store: ReplayStore | None = None,
        clock: Clock | None = None,
        system_id: int | None = None,
        allow_unsigned: frozenset[int] = frozenset(),
        max_streams: int = 256,
        reorder_window: int = 0,
        new_stream_max_age_s: float = 60.0,
        max_forward_s: float = 60.0,
        store_prefix: str = "mav",
    ) -> None:
        if len(key) != 32:
            raise ValueError("a MAVLink signing key is 32 bytes")
        self._key = key
        self.store = store
        self.clock = resolve(clock)
        self.system_id = system_id
        self.allow_unsigned = allow_unsigned
        self.max_streams = max_streams
        self.reorder_window = reorder_window
        self.new_stream_max_age = int(new_stream_max_age_s * UNITS_PER_S)
        self.max_forward = int(max_forward_s * UNITS_PER_S)
        self.prefix = store_prefix
        #: Source system ids that belong to the other direction (module docstring).
        self.refused_sources: set[int] = set() if system_id is None else {system_id}
        self._streams: OrderedDict[tuple[int, int, int], _Stream] = OrderedDict()
        self._fence = -1
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()

    def __len__(self) -> int:
        return len(self._streams)

    def check(self, raw: bytes) -> MavVerdict:
        """Accept one frame or raise a typed :class:`ReplayAttackError`."""
        frame = parse_frame(raw)
        if frame.sysid in self.refused_sources:
            raise WrongDirectionError(f"system {frame.sysid} sends from the other side of the link")
        if not frame.signed:
            if frame.msgid not in self.allow_unsigned:
                raise AuthenticationError(f"unsigned message {frame.msgid} not allow-listed")
            self._bind(frame)
            return MavVerdict(frame.stream, frame.msgid, 0, False)
        expected = hashlib.sha256(self._key + raw[:-6]).digest()[:6]
        if not hmac.compare_digest(expected, raw[-6:]):
            raise AuthenticationError("MAVLink signature does not verify")
        self._bind(frame)
        now = mav_time(self.clock)
        if frame.timestamp > now + self.max_forward:
            raise MessageFromFutureError("timestamp too far ahead of the receiver's clock")
        with self._lock:
            self._commit(frame, now)
        return MavVerdict(frame.stream, frame.msgid, frame.timestamp, True)

    def _bind(self, frame: Frame) -> None:
        if self.system_id is None:
            return
        target = target_system(frame)
        if target not in (None, 0, self.system_id):
            raise AuthenticationError(f"frame addressed to system {target}, not this vehicle")

    def _commit(self, frame: Frame, now: int) -> None:
        key, ts = frame.stream, frame.timestamp
        stream = self._streams.get(key)
        if stream is None:
            stream = self._open_stream(key, ts, now)
        if ts <= stream.floor:
            raise CounterReplayError("timestamp not newer than the persisted stream state")
        if stream.window is None:
            if ts <= stream.last:
                raise CounterReplayError("timestamp not newer than the stream's last")
        else:
            stream.window.check(ts)
            if not stream.window.accept(ts):
                raise CounterReplayError("timestamp already seen in the reorder window")
        if self.store is not None and not self.store.advance(self._store_key(key), ts):
            # Another guard on the same store (a second proxy, a restarted one still
            # running) already took this timestamp or a later one: this copy is a replay.
            raise CounterReplayError("timestamp already committed to the shared stream state")
        stream.last = max(stream.last, ts)
        self._streams[key] = stream
        self._streams.move_to_end(key)

    def _open_stream(self, key: tuple[int, int, int], ts: int, now: int) -> _Stream:
        stored = self.store.current(self._store_key(key)) if self.store is not None else None
        if stored is None:
            if ts < now - self.new_stream_max_age:
                raise MessageStaleError("new stream's timestamp is more than 60 s behind")
            if ts <= self._fence:
                raise MessageStaleError("new stream below the eviction fence")
        seen = -1 if stored is None else stored
        stream = _Stream(last=seen, floor=seen)
        if self.reorder_window:
            stream.window = CounterWindow(self.reorder_window, limit=TS_LIMIT)
        if len(self._streams) >= self.max_streams:
            _, evicted = self._streams.popitem(last=False)
            self._fence = max(self._fence, evicted.last)
        return stream

    def _store_key(self, key: tuple[int, int, int]) -> str:
        return f"{self.prefix}:{key[0]}:{key[1]}:{key[2]}"


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


@dataclass
class ProxyStats:
    """What the proxy did, per direction."""

    forwarded: Counter[str] = field(default_factory=Counter)
    dropped: Counter[str] = field(default_factory=Counter)


class MavlinkProxy:
    """UDP proxy: frames from the ground side go to the vehicle only if ``inbound`` accepts
    them; frames from the vehicle go back to the ground peer only if ``outbound`` accepts
    them.  ``on_reject`` receives each rejection (for audit and metrics).

    The ground peer (where telemetry goes) is learned only from a datagram in which at
    least one *signed* frame was accepted: garbage, forged or replayed frames, and
    unsigned allow-listed frames (anyone can make those), never move it, so one spoofed
    datagram cannot redirect the vehicle's telemetry.  Until a peer has authenticated,
    telemetry is dropped and counted as ``outbound:NO_PEER``.  Residual: an attacker who
    sees a ground frame before the proxy does can race it in from its own address; that
    frame is authentic and fresh, so the peer follows it (UDP carries no authenticated
    address; the same holds for every MAVLink endpoint).  Each side's authenticated
    source systems are refused on the other side (module docstring: direction binding).
    """

    def __init__(
        self,
        listen: tuple[str, int],
        forward: tuple[str, int],
        inbound: MavlinkGuard,
        outbound: MavlinkGuard,
        on_reject: Callable[[str, ReplayAttackError, bytes], Any] | None = None,
    ) -> None:
        self.ground = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.ground.bind(listen)
        self.vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.vehicle.connect(forward)
        for sock in (self.ground, self.vehicle):
            sock.settimeout(0.2)  # lets the loops notice stop() promptly
        self.inbound, self.outbound = inbound, outbound
        self.on_reject = on_reject
        self.stats = ProxyStats()
        self._peer: tuple[str, int] | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.ground.getsockname()[:2]
        return str(host), int(port)

    @property
    def peer(self) -> tuple[str, int] | None:
        """Where telemetry goes: the last ground address that sent an authenticated frame."""
        return self._peer

    def start(self) -> None:
        for target in (self._from_ground, self._from_vehicle):
            thread = threading.Thread(target=target, daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=5)
        for sock in (self.ground, self.vehicle):
            sock.close()

    def _filter(
        self, direction: str, guard: MavlinkGuard, other: MavlinkGuard, datagram: bytes
    ) -> tuple[bytes, bool]:
        """The accepted frames, and whether any of them was signed (authenticated)."""
        out, authenticated = bytearray(), False
        try:
            frames = split_frames(datagram)
        except ReplayAttackError as exc:
            self._reject(direction, exc, datagram)
            return b"", False
        for raw in frames:
            try:
                verdict = guard.check(raw)
            except ReplayAttackError as exc:
                self._reject(direction, exc, raw)
                continue
            if verdict.signed:
                authenticated = True
                other.refused_sources.add(verdict.stream[0])  # this side's system, from now on
            self.stats.forwarded[direction] += 1
            out += raw
        return bytes(out), authenticated

    def _reject(self, direction: str, exc: ReplayAttackError, raw: bytes) -> None:
        self.stats.dropped[f"{direction}:{exc.code}"] += 1
        if self.on_reject is not None:
            self.on_reject(direction, exc, raw)

    def _from_ground(self) -> None:
        while not self._stop.is_set():
            try:
                datagram, peer = self.ground.recvfrom(65_535)
            except TimeoutError:
                continue
            except OSError:
                return
            allowed, authenticated = self._filter("inbound", self.inbound, self.outbound, datagram)
            if authenticated:
                self._peer = peer
            if allowed:
                try:
                    self.vehicle.send(allowed)
                except OSError:
                    self.stats.dropped["inbound:VEHICLE_UNREACHABLE"] += 1

    def _from_vehicle(self) -> None:
        while not self._stop.is_set():
            try:
                datagram = self.vehicle.recv(65_535)
            except TimeoutError:
                continue
            except (ConnectionRefusedError, ConnectionResetError):
                continue  # the vehicle is not up yet: ICMP port unreachable
            except OSError:
                return
            allowed, _ = self._filter("outbound", self.outbound, self.inbound, datagram)
            if not allowed:
                continue
            peer = self._peer
            if peer is None:
                self.stats.dropped["outbound:NO_PEER"] += 1
                continue
            try:
                self.ground.sendto(allowed, peer)
            except OSError:
                self.stats.dropped["outbound:GROUND_UNREACHABLE"] += 1
