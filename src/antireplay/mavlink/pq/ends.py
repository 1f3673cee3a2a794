"""The two ends of a PQ link: the ground end (initiator) and the vehicle end (responder).

Sans-I/O: bytes and a time in, frames out; :mod:`.link` drives them over transports and
calls :meth:`GroundEnd.tick` on a timer, so that a lost handshake is retried every
``retry_s`` whether or not local traffic arrives.  Each end says which session is
:attr:`~GroundEnd.live` (held, and something authenticated heard from the other end
within ``silence_s``) and counts its handshakes (``started``, ``completed``, ``failed``:
superseded unanswered, or refused) and the local frames it dropped (``NO_SESSION``...).
"""

from __future__ import annotations

import secrets
from collections import Counter, deque
from dataclasses import dataclass, field

from cryptography.hazmat.primitives.asymmetric import mlkem, x25519

from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import (
    InvalidFrameError,
    ReplayAttackError,
    SignatureInvalidError,
    SignatureRequiredError,
    UnknownSessionError,
)
from antireplay.mavlink.codec import Frame, parse_frame
from antireplay.mavlink.pq.chunks import (
    ChunkSender,
    PlainFrameError,
    Reassembler,
    ReassemblyStats,
    chunk_key,
    parse_chunk,
)
from antireplay.mavlink.pq.wire import (
    _COMPACT,
    _INNER_HEAD,
    MSG_STATUS,
    REKEY_TRANSFERS,
    SIGNED_MESSAGES,
    STATUS_NO_SESSION,
    TRANSFER_LIMIT,
    ChunkKind,
    compact,
    inner_of,
    open_compact,
    plain_frame,
    read_status,
    status_frame,
)
from antireplay.pq.session import (
    Direction,
    Initiator,
    Purpose,
    Responder,
    Session,
)


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
        self.handshakes: Counter[str] = Counter()

    def handshake(self) -> list[bytes]:
        """Start a new handshake (the current session keeps working until HS2 arrives).  Its
        transfer number is random: nobody can plant a conflicting chunk ahead of it."""
        if self._pending is not None:
            self.handshakes["failed"] += 1  # never answered: superseded
        self.handshakes["started"] += 1
        hs1 = self.initiator.start(self.responder_key, self.hybrid)
        self._pending = (hs1, self._clock.monotonic())
        return self.sender.frames(hs1, ChunkKind.HS1, transfer=secrets.randbelow(0x10000))

    def from_local(self, raw: bytes) -> list[bytes]:
        """Wrap one plain frame from a local peer.  While there is no session, commands wait
        in a bounded queue, each at most ``queue_ttl_s`` (a command is meant for now, not
        for whenever the link comes back), and the rest is dropped: a heartbeat comes
        again, and must not push a command out of the queue.  Every drop is counted in
        :attr:`drops`."""
        frame = _parse(raw)
        session = self._usable()
        if session is None:
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
        return self._seal(session, inner_of(frame), purpose) + self._renew(session)

    def tick(self) -> list[bytes]:
        """What time alone calls for: expire queued commands, and hand-shake again (at most
        every ``retry_s``) while there is no session or this one should end (:meth:`_renew`)."""
        self._expire_queue()
        session = self._usable()
        return self._retry() if session is None else self._renew(session)

    @property
    def live(self) -> Session | None:
        """The session, while the vehicle was heard within ``silence_s``."""
        silent = self._clock.monotonic() - self._heard >= self.silence_s
        return None if silent else self.session

    def _usable(self) -> Session | None:
        if self.session is not None and self._transfers_used() >= TRANSFER_LIMIT:
            self.session = None  # its transfer numbers would wrap: wait for the new one
        return self.session

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
        return self.sender.frames(blob, ChunkKind.FRAME, chunk_key(session.send_key))

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
        if kind is ChunkKind.HS2:
            return self._finish(blob)
        if kind not in (ChunkKind.FRAME, ChunkKind.FRAME_CHUNKED) or self.session is None:
            raise UnknownSessionError(f"{kind.name} blob with no session to take it")
        opened = open_compact(blob, [self.session], Direction.R2I, self.session)
        self._reassembler.opened(chunk, keys[0])
        self._heard = self._clock.monotonic()
        return Output(local=[plain_frame(opened.payload)], authenticated=True)

    def _finish(self, hs2: bytes) -> Output:
        if self._pending is None:
            raise UnknownSessionError("HS2 with no handshake in progress")
        self.session = self.initiator.finish(self._pending[0], hs2)
        self.handshakes["completed"] += 1
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
        silence_s: float = 5.0,
        signed: frozenset[int] = SIGNED_MESSAGES,
        clock: Clock | None = None,
    ) -> None:
        self.responder = responder
        self.silence_s = silence_s
        self.signed = signed  # messages delivered only from a command (ML-DSA-87) frame
        self.sender = ChunkSender(system_id, component_id)
        self.hint_interval_s = hint_interval_s
        self._clock = resolve(clock)
        self._reassembler = Reassembler(clock=clock)
        self._sessions: deque[Session] = deque(maxlen=responder.max_sessions)
        self.current: Session | None = None  # the newest session that authenticated
        self._hinted = float("-inf")
        self._heard = float("-inf")  # when an authenticated blob last came from the ground
        #: Telemetry dropped because no session carries it yet (``NO_SESSION``).
        self.drops: Counter[str] = Counter()
        self.handshakes: Counter[str] = Counter()

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
        if kind is ChunkKind.HS1:
            handles = {s.session_id[-1] for s in self._sessions}
            self.handshakes["started"] += 1
            try:
                session, hs2 = self.responder.accept_handshake(blob, lambda sid: sid[-1] in handles)
            except ReplayAttackError:
                self.handshakes["failed"] += 1
                raise
            self.handshakes["completed"] += 1
            self._sessions.append(session)
            self.current, self._heard = session, self._clock.monotonic()
            return Output(air=self.sender.frames(hs2, ChunkKind.HS2), authenticated=True)
        if kind is ChunkKind.HS2:
            raise InvalidFrameError("HS2 travels to the ground end")
        self._require_signature(blob)
        opened = open_compact(blob, self._sessions, Direction.I2R, self.responder)
        session = next(s for s in self._sessions if s.session_id == opened.session_id)
        self._reassembler.opened(chunk, chunk_key(session.recv_key))
        self._supersede(session)
        self.current, self._heard = session, self._clock.monotonic()
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
        """Wrap one telemetry frame from the flight controller; with no session it is
        dropped and counted (:attr:`drops`): the flight controller streams long before
        the ground end connects, which is no fault."""
        frame = _parse(raw)
        if self.current is None:
            self.drops["NO_SESSION"] += 1
            return []
        blob = compact(self.current.seal(inner_of(frame), Purpose.DATA))
        return self.sender.frames(blob, ChunkKind.FRAME, chunk_key(self.current.send_key))

    def tick(self) -> list[bytes]:
        """Nothing to send on time alone: the ground end opens sessions."""
        return []

    @property
    def live(self) -> Session | None:
        """The current session, while the ground end was heard within ``silence_s``."""
        silent = self._clock.monotonic() - self._heard >= self.silence_s
        return None if silent else self.current

    @property
    def reassembly(self) -> ReassemblyStats:
        return self._reassembler.stats
