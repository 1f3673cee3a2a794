"""The two post-quantum ends on the wire: each joins a local transport and an air transport.

Theory of operation
-------------------
A :class:`PqLink` moves bytes for one sans-I/O end of :mod:`antireplay.mavlink.pq`
between two :class:`~antireplay.mavlink.endpoints.Transport` s.  The **ground** end's
``local`` is where ground stations connect (a trusted ``udpin``: every peer that sends
receives the telemetry), ``air`` the path to the vehicle; it hand-shakes at
:meth:`~PqLink.start` and, from a timer (:meth:`~PqLink.tick`, every ``tick_s``), pokes
and hand-shakes again (:mod:`.ground`) until a session answers, whether or not local traffic
arrives; the timer also drives repair requests for transfers gone quiet.  The
**vehicle** end's ``local`` is the flight controller, ``air`` the path to the ground; a
``udpin`` air peer is learned only from the first blob of each session that
authenticated (until then a handshake's repair request, at once or on the timer, goes
to the sender of the last chunk that was not refused, never learned; a repair frame
never steers it), and plain MAVLink from the air never
reaches the flight controller.

Every refusal is counted under ``side:CODE`` and handed to ``on_reject`` (the
rate-limited refusal auditor the command gives it; a refusal it could not record is
counted ``unaudited``), except plain MAVLink on the air (routers' heartbeats: counted
``air:PLAIN``).  What an end drops without an error is counted too (:attr:`~PqLink.dropped`),
telemetry with no session among it: never logged per frame.  A vehicle end answers a
frame for a session it does not hold with the rate-limited ``PQ_STATUS`` hint, and a
refused HS1 with its ``PQ_REFUSAL`` (:mod:`.vehicle`); a ground end hands a verified
refusal's reason to ``on_notice`` (once per reason until a session comes up).  Each
change of the live session (``established``, ``rekeyed``, ``lost``: nothing
authenticated from the other end for ``silence_s``, ``resumed``) is counted and handed
once to ``on_session`` (authentic: always recorded).  :meth:`~PqLink.counts` is what
the metrics export, airtime by kind among it.  One lock serialises the end; writes
happen outside it.  With ``air_bps`` (the radio's serial rate in baud, 10 bits a byte)
a :class:`Pacer` (a token bucket of bytes at 97 % of the line rate, a tenth of a second
of burst: well within a SiK radio's 2,048-byte buffer at 57,600 baud) puts frames on
the air no faster than the radio carries them, one-chunk frames (telemetry, ACKs,
repair requests, HS2) ahead of the chunks of long transfers, so telemetry keeps flowing
between a command's chunks, yet never all of the line: while both wait, long transfers
get a byte for each byte of one-chunk frames (``BULK_SHARE``), so a saturating RC
override cannot starve a command or a handshake.  Telemetry beyond two seconds of queue
is dropped (``air:PACED_OUT``), and so is a long transfer's chunk still queued after
``bulk_ttl_s`` (``air:PACED_STALE``): the GCS has given up on it, and it must not leave
late (an HS1's chunks never expire: they take 10 s at 7,200 baud, and the handshake
budget, :mod:`.ground`, already spaces them).
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import AntiReplayError, Code, ReplayAttackError
from antireplay.core.ratelimit import TokenBucket
from antireplay.mavlink.codec import Frame
from antireplay.mavlink.endpoints import Peer, Transport
from antireplay.mavlink.links import FrameRefusal
from antireplay.mavlink.pq.chunks import PlainFrameError
from antireplay.mavlink.pq.ground import GroundEnd
from antireplay.mavlink.pq.repair import Output, air_kind
from antireplay.mavlink.pq.vehicle import VehicleEnd
from antireplay.mavlink.pq.wire import LINE_BITS, ChunkKind
from antireplay.pq.session import Session

_HINTED = {Code.UNKNOWN_SESSION, Code.SESSION_CLOSED}
#: The kinds of :class:`SessionEvent`, in the order the metrics list them.
SESSION_EVENTS = ("established", "rekeyed", "lost", "resumed")


@dataclass(frozen=True)
class SessionEvent:
    """A change of an end's live session, logged and audited once."""

    end: str  # ground or vehicle
    kind: str  # one of SESSION_EVENTS
    session_id: bytes
    peer: str

    def __str__(self) -> str:
        return f"pq {self.end}: session {self.kind} ({self.session_id.hex()}, peer {self.peer})"


@dataclass(frozen=True)
class LinkCounts:
    """A snapshot of everything a link counts (what its metrics export)."""

    end: str
    up: bool
    sessions: Counter[str]
    handshakes: Counter[str]
    chunks: Counter[str]  # sent, received (not plain MAVLink), reassembled (whole blobs)
    refused: Counter[str]  # side:CODE
    dropped: Counter[str]  # side:REASON, dropped without a refusal
    unaudited: int
    airtime: Counter[str] = field(default_factory=Counter)  # air bytes by kind (AIR_KINDS)
    repairs: Counter[str] = field(default_factory=Counter)  # NACKs, POKEs, resent chunks
    retries: Counter[str] = field(default_factory=Counter)  # GCS retries, how answered
    handshake_refusals: Counter[str] = field(default_factory=Counter)  # PQ_REFUSALs


#: The pacer's share of the line rate (the radio's own clock and a busy host both drift),
#: and the longest frame an end sends (a full ``PQ_CHUNK``).
PACE, MAX_FRAME = 0.97, 10 + 255 + 2
#: Bytes of long transfers a pacer owes for each byte of one-chunk frames while both wait.
BULK_SHARE = 1.0


class Pacer:
    """Frames for the air, released no faster than ``air_bps`` (module docstring)."""

    def __init__(
        self, air_bps: int, clock: Clock | None = None, *, bulk_ttl_s: float = 6.0
    ) -> None:
        rate = PACE * air_bps / LINE_BITS  # bytes a second, a little under the line's
        burst = max(rate / 10, 2 * MAX_FRAME)  # a tenth of a second; two frames at least
        self._clock = resolve(clock)
        self.bucket = TokenBucket(rate, self._clock, burst=burst)
        self.limit = int(2 * rate)  # bytes of telemetry queued at most
        self.bulk_ttl_s = bulk_ttl_s  # a GCS's retry horizon: a chunk older is dropped
        self.urgent: deque[tuple[bytes, Peer | None]] = deque()
        self.bulk: deque[tuple[bytes, Peer | None]] = deque()
        self._born: deque[float] = deque()  # when each bulk frame was queued
        self._owed = 0.0  # bulk bytes owed for the one-chunk bytes sent while bulk waited
        self.queued = 0
        self.paced_out = 0
        self.paced_stale = 0

    def push(self, frames: list[bytes], peer: Peer | None) -> None:
        for raw in frames:
            kind = air_kind(raw)
            if kind in ("cmd", "parity") or (kind == "hs" and len(frames) > 1):
                self.bulk.append((raw, peer))
                # a handshake's chunks (parity too) never go stale: no GCS waits on them,
                # and on a slow radio (7,200 baud: 10 s for an HS1) a TTL cuts them short
                handshake = ChunkKind(raw[15] & 0x0F) in (ChunkKind.HS1, ChunkKind.HS2)
                self._born.append(float("inf") if handshake else self._clock.monotonic())
            elif kind == "passthrough" and self.queued > self.limit:
                self.paced_out += 1
                continue
            else:
                self.urgent.append((raw, peer))
            self.queued += len(raw)

    def pop(self) -> tuple[list[tuple[bytes, Peer | None]], float]:
        """The frames that may go now, and the seconds until the next one may."""
        out: list[tuple[bytes, Peer | None]] = []
        self._expire()
        while self.urgent or self.bulk:
            bulk = bool(self.bulk) and (not self.urgent or self._owed >= len(self.bulk[0][0]))
            queue = self.bulk if bulk else self.urgent
            raw = queue[0][0]
            if not self.bucket.take(len(raw)):
                return out, max(self.bucket.wait_s(len(raw)), 0.001)  # time moves on
            out.append(queue.popleft())
            self.queued -= len(raw)
            if bulk:
                self._born.popleft()
                self._owed = max(0.0, self._owed - len(raw))
            elif self.bulk:
                self._owed += BULK_SHARE * len(raw)
        self._owed = 0.0
        return out, 1.0

    def _expire(self) -> None:
        """Drop long transfers' chunks queued over ``bulk_ttl_s`` (counted)."""
        horizon = self._clock.monotonic() - self.bulk_ttl_s
        while self._born and self._born[0] < horizon:
            self._born.popleft()
            self.queued -= len(self.bulk.popleft()[0])
            self.paced_stale += 1


class PqLink:
    """One end (ground or vehicle) between its local and its air transport."""

    def __init__(
        self,
        end: GroundEnd | VehicleEnd,
        local: Transport,
        air: Transport,
        *,
        on_reject: Callable[[FrameRefusal], Any] | None = None,
        on_session: Callable[[SessionEvent], Any] | None = None,
        on_notice: Callable[[str], Any] | None = None,
        tap: Callable[[bytes], Any] | None = None,
        max_local_peers: int = 8,
        tick_s: float = 0.1,
        air_bps: int | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.end, self.local, self.air = end, local, air
        self.name = "ground" if isinstance(end, GroundEnd) else "vehicle"
        self.on_reject, self.on_session, self.tap = on_reject, on_session, tap
        self.on_notice = on_notice  # what the operator must hear once (a refused handshake)
        self.max_local_peers, self.tick_s = max_local_peers, tick_s
        self._dropped: Counter[str] = Counter()
        self._refused: Counter[str] = Counter()
        self.forwarded: Counter[str] = Counter()
        self.sessions: Counter[str] = Counter()
        self.chunks: Counter[str] = Counter()
        self.air_bytes = 0
        self._local_peers: dict[Peer, None] = {}
        self._air_peer: Peer | None = None
        self._replied: Peer | None = None  # the sender of the last chunk not refused
        self._learned: Session | None = None  # the session the air peer was learned in
        self._live: Session | None = None
        self._last: Session | None = None  # the last session that was live
        self._lock = threading.Lock()
        self._count_lock = threading.Lock()
        self._stopped = threading.Event()
        self._ticker: threading.Thread | None = None
        self.pacer = None if air_bps is None else Pacer(air_bps, clock)
        self._paced = threading.Condition()
        self._pacing: threading.Thread | None = None

    def start(self) -> None:
        """Start both transports and the timer; a ground end sends its first handshake."""
        self.local.start(self._from_local)
        self.air.start(self._from_air)
        if isinstance(self.end, GroundEnd):
            with self._lock:
                frames = self.end.handshake()
            self._to_air(frames, None)
        self._ticker = threading.Thread(target=self._tick_loop, name="pq-tick", daemon=True)
        self._ticker.start()
        if self.pacer is not None:
            self._pacing = threading.Thread(target=self._pace_loop, name="pq-pace", daemon=True)
            self._pacing.start()

    def stop(self) -> None:
        self._stopped.set()
        with self._paced:
            self._paced.notify()
        for thread in (self._ticker, self._pacing):
            if thread is not None:
                thread.join()
        self.local.close()
        self.air.close()

    def _tick_loop(self) -> None:
        while not self._stopped.wait(self.tick_s):
            self.tick()

    def tick(self) -> None:
        """What time alone calls for: the end's retries and expiries, a lost session noticed."""
        with self._lock:
            frames = self.end.tick()
        self._to_air(frames, self._air_peer or self._replied)  # a handshake's NACK, say
        self._observe()

    def _pace_loop(self) -> None:
        assert self.pacer is not None
        while not self._stopped.is_set():
            with self._paced:
                ready, wait_s = self.pacer.pop()
                if not ready:
                    self._paced.wait(wait_s)
                    continue
            self._send_air(ready)

    def _from_local(
        self, transport: Transport, peer: Peer | None, frames: list[Frame], skipped: int
    ) -> None:
        if skipped:
            self._refuse("local", Code.INVALID_FRAME, f"{skipped} bytes that are no frame", b"")
        if peer is not None and peer not in self._local_peers:
            self._local_peers[peer] = None
            if len(self._local_peers) > self.max_local_peers:
                del self._local_peers[next(iter(self._local_peers))]
        for frame in frames:
            raw = frame.raw
            try:
                with self._lock:
                    out = self.end.handle_local(raw)
            except ReplayAttackError as exc:
                self._refuse("local", exc.code, exc.reason, raw)
                continue
            self.forwarded["local"] += 1
            for data in out.local:  # a GCS retry answered with the ACK already seen
                self._to_local(data)
            self._to_air(out.air, self._air_peer)
        self._observe()

    def _from_air(
        self, transport: Transport, peer: Peer | None, frames: list[Frame], skipped: int
    ) -> None:
        if skipped:
            self._refuse("air", Code.INVALID_FRAME, f"{skipped} bytes that are no frame", b"")
        for frame in frames:
            raw, hint = frame.raw, []
            try:
                with self._lock:
                    out: Output = self.end.from_air(raw)
            except PlainFrameError:  # a router's own heartbeat, say: counted, not reported
                self._count("air:PLAIN")
                continue
            except ReplayAttackError as exc:
                self._count("received", counter=self.chunks)
                self._refuse("air", exc.code, exc.reason, raw)
                if isinstance(self.end, VehicleEnd):
                    with self._lock:
                        hint = self.end.hint() if exc.code in _HINTED else []
                        hint += self.end.answered()  # a refused HS1's PQ_REFUSAL
                self._to_air(hint, peer)
                continue
            self._count("received", counter=self.chunks)
            if out.notice is not None and self.on_notice is not None:
                self.on_notice(out.notice)
            if out.authenticated:
                self._learn(peer)
                self.forwarded["air"] += 1
            for data in out.local:
                self._to_local(data)
            if peer is not None and air_kind(raw) != "repair":  # a chunk, taken: where time
                self._replied = peer  # alone may answer a handshake (never learned)
            self._to_air(out.air, peer if out.authenticated or out.reply else self._air_peer)
        self._observe()

    def _learn(self, peer: Peer | None) -> None:
        """The air peer: the sender of the first authenticated blob of each session (a
        relayed copy of a later chunk, arriving first, steers nothing)."""
        with self._lock:
            end = self.end
            session = end.session if isinstance(end, GroundEnd) else end.current
        if session is not self._learned or self._air_peer is None:
            self._air_peer, self._learned = peer, session

    def _observe(self) -> None:
        """Hand a change of the live session to ``on_session``, once."""
        with self._lock:
            live, before = self.end.live, self._live
            if live is before:
                return
            self._live = live
            if live is None:
                assert before is not None
                kind, session = "lost", before
            else:
                kind = "rekeyed" if before is not None else "established"
                if live is self._last:
                    kind = "resumed"
                self._last = session = live
        self._count(kind, counter=self.sessions)
        event = SessionEvent(self.name, kind, session.session_id, session.peer_id)
        if self.on_session is None:
            return
        try:
            self.on_session(event)
        except AntiReplayError:
            self._count("unaudited")

    def _to_local(self, data: bytes) -> None:
        peers: list[Peer | None] = [None] if self.local.fixed else list(self._local_peers)
        for peer in peers:
            if not self.local.send(data, peer):
                self._count("local:UNREACHABLE")

    def _to_air(self, frames: list[bytes], peer: Peer | None) -> None:
        if not frames:
            return
        if peer is None and not self.air.fixed:
            self._count("air:NO_PEER", len(frames))
            return
        if self.pacer is not None:
            with self._paced:
                self.pacer.push(frames, peer)
                self._paced.notify()
            return
        self._send_air([(data, peer) for data in frames])

    def _send_air(self, frames: list[tuple[bytes, Peer | None]]) -> None:
        self._count("sent", len(frames), self.chunks)
        for data, peer in frames:
            if self.tap is not None:
                self.tap(data)
            self.air_bytes += len(data)
            if not self.air.send(data, peer):
                self._count("air:UNREACHABLE")

    @property
    def dropped(self) -> Counter[str]:
        """Everything dropped, by ``side:REASON``: refusals (``side:CODE``), what the end
        threw away without an error (reassembly: ``air:EVICTED``, ``air:EXPIRED``,
        ``air:DUPLICATE``; local messages that never left: ``local:NO_SESSION`` at either
        end, a ground end's ``local:QUEUE_FULL``, ``local:QUEUE_EXPIRED``), plain
        MAVLink on the air (``air:PLAIN``) and what could not be written."""
        with self._lock:
            stats = self.end.reassembly
            out = Counter(
                {
                    "air:EVICTED": stats.evicted,
                    "air:EXPIRED": stats.expired,
                    "air:DUPLICATE": stats.duplicates,
                }
            )
            out.update({f"local:{k}": v for k, v in self.end.drops.items()})
        if self.pacer is not None:
            with self._paced:
                out["air:PACED_OUT"] = self.pacer.paced_out
                out["air:PACED_STALE"] = self.pacer.paced_stale
        with self._count_lock:
            out.update(self._dropped)
            out.update(self._refused)
        return +out  # the zero counts dropped

    def counts(self) -> LinkCounts:
        """Everything counted, now: refusals apart from the other drops."""
        with self._lock:
            handshakes = Counter(self.end.handshakes)
            reassembled = self.end.reassembly.reassembled
            up = self.end.live is not None
            airtime, repairs = Counter(self.end.airtime), Counter(self.end.repairs)
            retries = Counter(self.end.retries)
            handshake_refusals = Counter(self.end.refusals)
        dropped = self.dropped
        with self._count_lock:
            refused = Counter(self._refused)
            sessions, chunks = Counter(self.sessions), Counter(self.chunks)
        chunks["reassembled"] = reassembled
        unaudited = dropped.pop("unaudited", 0)
        dropped.subtract(refused)
        return LinkCounts(
            self.name, up, sessions, handshakes, chunks, refused, +dropped, unaudited,
            airtime, repairs, retries, handshake_refusals,
        )  # fmt: skip

    def _count(self, key: str, n: int = 1, counter: Counter[str] | None = None) -> None:
        with self._count_lock:
            (self._dropped if counter is None else counter)[key] += n

    def _refuse(self, side: str, code: str, reason: str, raw: bytes) -> None:
        self._count(f"{side}:{code}", counter=self._refused)
        if self.on_reject is None:
            return
        try:
            self.on_reject(FrameRefusal(side, f"pq {side}", str(code), reason, raw))
        except AntiReplayError:
            self._count("unaudited")
