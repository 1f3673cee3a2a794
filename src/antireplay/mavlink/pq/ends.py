"""The two ends of a PQ link: the ground end (initiator) and the vehicle end (responder).

Sans-I/O: bytes and a time in, frames out; :mod:`.link` drives them over transports and
calls ``tick`` on a timer, so that a transfer gone quiet is repaired (:mod:`.repair`)
and a lost handshake is poked, then retried, whether or not local traffic arrives: the
ground end POKEs its HS1 ``poke_s`` after its chunks left (by ``air_bps``) or were last
repaired (twice at most; the vehicle end answers with its held HS2 or a NACK), and
hand-shakes anew only after ``retry_s`` of quiet, so repairs never race a new HS1.
Each end says which session is :attr:`~GroundEnd.live` (held, and something
authenticated heard from the other end within ``silence_s``) and counts its handshakes
(``started``, ``completed``, ``failed``: superseded unanswered, or refused), the local
frames it dropped (``NO_SESSION``...), its repairs, a GCS's retries and its airtime.

A GCS retry (:meth:`GroundEnd.handle_local`) is keyed on what the ground end itself
sealed and sent: a later identical command within ``retry_window_s`` of the first try
(a fixed window, a GCS's whole retry horizon: repeats never keep it open)
asks the vehicle end, by an authenticated POKE naming that transfer (and a fresh nonce),
for what it holds.  The vehicle end answers for a transfer that opened with its held
``COMMAND_ACK`` sealed anew (at most ``MAX_ANSWERS`` times) and delivers nothing again;
for one that never opened and never can (a later one did), "not delivered" echoing the
nonce, and the ground end sends that command anew, whole.  Every ACK the vehicle end
holds travels bound to the transfer it answers (:func:`~.repair.bind_ack`, inside the
seal): the ground end gives a try only its own transfer's ACK, and passes on none twice
nor one for a try it no longer has, so a replayed POKE, or another command with the same
number, never tells a GCS that a command it sent was accepted.  A command repeated on
purpose within that window is answered, not executed: repeat it after the window.

A command also carries, sealed with it, when the ground end sealed it: milliseconds since
its session came up there (the HS2 arrived).  The vehicle end refuses (``MESSAGE_STALE``,
counted in ``drops``) a command older than ``max_age_s`` by its own time since it sent
that HS2.  No clocks are compared: each end measures from its side of one event, and the
vehicle's side comes first (the HS2 leaves before it arrives), so the vehicle reckons a
command older than it is, never younger: a command withheld on the air and released
later is refused however the attacker times it (delaying HS2 only ages every command).

Size: over 500 lines: the two ends share their rules (:class:`~.repair.RepairingEnd`)
but each is one state machine over its half of the handshake, kept whole.
"""

from __future__ import annotations

import secrets
import struct
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

from cryptography.hazmat.primitives.asymmetric import mlkem, x25519
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.core.clock import Clock
from antireplay.core.errors import (
    InvalidFrameError,
    MessageStaleError,
    ReplayAttackError,
    SignatureInvalidError,
    SignatureRequiredError,
    UnknownSessionError,
)
from antireplay.core.ratelimit import TokenBucket
from antireplay.mavlink.codec import parse_frame
from antireplay.mavlink.pq.chunks import (
    Chunk,
    chunk_key,
    parse_chunk,
)
from antireplay.mavlink.pq.repair import (
    EVERYTHING,
    IN_PROGRESS,
    MAX_ANSWERS,
    RETRIED,
    Op,
    Output,
    Repair,
    RepairingEnd,
    _parse,
    bind_ack,
    bitmap,
    command_of,
    parse_repair,
    repair_frame,
    repair_key,
    retry_key,
    unbind_ack,
)
from antireplay.mavlink.pq.wire import (
    _COMPACT,
    _INNER_HEAD,
    LINE_BITS,
    MSG_REPAIR,
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

_STAMP = struct.Struct("<I")  # a command's age stamp: ms since its session came up (ground)


@dataclass
class _Try:
    """A command the ground end sent: its transfer, its session, the ACK once seen."""

    transfer: int
    session: Session
    command: int
    first: float  # when the GCS first sent it: the retry window runs from here, fixed
    due: float  # when its last chunk should have left (by air_bps)
    raw: bytes  # the GCS's frame, sealed anew if the vehicle end says it never arrived
    ack: bytes | None = None
    nonce: int = 0  # the outstanding POKE's, echoed in a "not delivered" answer (0: none)


class GroundEnd(RepairingEnd):
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
        poke_s: float = 0.5,
        gap_s: float = 0.25,
        retry_window_s: float = 6.0,
        air_bps: int | None = None,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(system_id, component_id, gap_s, clock)
        self.initiator, self.responder_key = initiator, responder_key
        self.hybrid = hybrid  # the vehicle's static X25519 key: hybrid handshakes
        self.signed = signed
        self.retry_s, self.silence_s = retry_s, silence_s
        self.poke_s, self.retry_window_s, self.air_bps = poke_s, retry_window_s, air_bps
        self._first_transfer = 0  # the sender's transfer number when the session began
        self.session: Session | None = None
        self._pending: tuple[bytes, float] | None = None  # HS1 and when it left
        self._hs_transfer, self._hs_quiet, self._hs_pokes = 0, 0.0, 0
        self._hs_keyed = False  # the pending HS1 is a rekey's: unsigned NACKs are refused
        self._hs2: bytes | None = None  # the HS2 that finished the session (a repeat is no news)
        self.max_queued, self.queue_ttl_s = max_queued, queue_ttl_s
        self._queue: deque[tuple[bytes, float]] = deque()  # commands and when they came
        self._tries: OrderedDict[tuple[int, int, int, bytes], _Try] = OrderedDict()
        self._last_ack, self._last_ack_at = b"", float("-inf")  # the ACK last passed on
        self._heard = float("-inf")  # when an authenticated frame last came from the vehicle
        self._epoch = 0.0  # when this session came up here (HS2): commands' age stamps
        # drops: NO_SESSION (not a command, no session), QUEUE_FULL (the oldest queued
        # command, pushed out by a newer one), QUEUE_EXPIRED (waited over queue_ttl_s)

    def _sessions_held(self) -> list[Session]:
        return [] if self.session is None else [self.session]

    def _airtime_s(self, frames: list[bytes]) -> float:
        """How long ``frames`` take on a radio of ``air_bps`` baud (0 when unknown)."""
        return 0.0 if not self.air_bps else LINE_BITS * sum(map(len, frames)) / self.air_bps

    def handshake(self) -> list[bytes]:
        """Start a new handshake (the current session keeps working until HS2 arrives).  Its
        transfer number is random: nobody can plant a conflicting chunk ahead of it."""
        if self._pending is not None:
            self.handshakes["failed"] += 1  # never answered: superseded
            self._sent.forget(self._hs_transfer)
        self.handshakes["started"] += 1
        hs1 = self.initiator.start(self.responder_key, self.hybrid)
        now = self._clock.monotonic()
        self._pending = (hs1, now)
        self._hs_transfer = secrets.randbelow(0x10000)
        frames = self.sender.frames(hs1, ChunkKind.HS1, transfer=self._hs_transfer)
        live = self.live  # a rekey: its NACKs must come MACed in the live session
        self._hs_keyed = live is not None
        key = None if live is None else repair_key(live.recv_key)
        self._sent.add(self._hs_transfer, frames, key)
        self._hs_quiet, self._hs_pokes = now + self._airtime_s(frames), 0
        return self._air(frames)

    def from_local(self, raw: bytes) -> list[bytes]:
        """:meth:`handle_local`'s air frames."""
        return self.handle_local(raw).air

    def handle_local(self, raw: bytes) -> Output:
        """Wrap one plain frame from a local peer.  While there is no session, commands wait
        in a bounded queue, each at most ``queue_ttl_s`` (a command is meant for now, not
        for whenever the link comes back), and the rest is dropped: a heartbeat comes
        again, and must not push a command out of the queue.  Every drop is counted in
        :attr:`drops`.  A GCS's retry of a command in flight (same source, target, command
        and parameters within ``retry_window_s`` of the first try) is no new transfer: a
        POKE asks the vehicle end where it stands, or the ACK already seen answers it."""
        frame = _parse(raw)
        session = self._usable()
        tried = retry_key(frame)
        if session is None:
            if frame.msgid in self.signed:
                self._expire_queue()
                if tried is not None and any(tried == retry_key(_parse(q)) for q, _ in self._queue):
                    self.retries["queued"] += 1
                    return Output(air=self._retry())
                if len(self._queue) >= self.max_queued:
                    self._queue.popleft()
                    self.drops["QUEUE_FULL"] += 1
                self._queue.append((raw, self._clock.monotonic()))
            else:
                self.drops["NO_SESSION"] += 1
            return Output(air=self._retry())
        if tried is not None:
            answer = self._answer_retry(tried, session)
            if answer is not None:
                return answer
        purpose = Purpose.COMMAND if frame.msgid in self.signed else Purpose.DATA
        air = self._seal(session, inner_of(frame), purpose)
        if tried is not None:
            now = self._clock.monotonic()
            due = now + self._airtime_s(air)
            transfer = self.sender.transfer
            self._tries[tried] = _Try(transfer, session, command_of(frame), now, due, raw)
            while len(self._tries) > self._sent.max_transfers:
                self._tries.popitem(last=False)
        return Output(air=air + self._renew(session))

    def _answer_retry(self, tried: tuple[int, int, int, bytes], session: Session) -> Output | None:
        attempt, now = self._tries.get(tried), self._clock.monotonic()
        if attempt is None or attempt.session is not session:
            return None
        if now - attempt.first > self.retry_window_s:
            del self._tries[tried]
            return None
        if attempt.ack is not None:
            self.retries["answered"] += 1
            return Output(local=[attempt.ack])
        if now < attempt.due:  # its chunks are still going out: nothing to ask yet
            self.retries["sending"] += 1
            return Output()
        self.retries["poked"] += 1
        self.repairs["poke_sent"] += 1
        attempt.nonce = secrets.randbits(63) | 1
        poke = repair_frame(
            Op.POKE, attempt.transfer, (0, 0), attempt.nonce, repair_key(session.send_key),
            sysid=self.sender.sysid, compid=self.sender.compid,
        )  # fmt: skip
        return Output(air=self._air([poke], "repair"))

    def tick(self) -> list[bytes]:
        """What time alone calls for: expire queued commands, ask for chunks of transfers
        that went quiet, and poke or hand-shake again (:meth:`_retry`) while there is
        no session or this one should end (:meth:`_renew`)."""
        self._expire_queue()
        session = self._usable()
        out = self._stale_nacks()
        return out + (self._retry() if session is None else self._renew(session))

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
        """Seal a frame; a command with its age stamp (module docstring)."""
        if purpose is Purpose.COMMAND:
            age_ms = int(max(0.0, self._clock.monotonic() - self._epoch) * 1000)
            inner += _STAMP.pack(min(age_ms, 0xFFFFFFFF))
        blob = compact(session.seal(inner, purpose))
        frames = self.sender.frames(blob, ChunkKind.FRAME, chunk_key(session.send_key))
        self._sent.add(self.sender.transfer, frames, repair_key(session.recv_key))
        return self._air(frames)

    def _retry(self) -> list[bytes]:
        """The pending handshake's timer: quiet for ``poke_s`` after its chunks left (by
        ``air_bps``) or were last repaired, a POKE (twice at most: the HS2 may be lost, or
        the tail of HS1); quiet for ``retry_s``, a new handshake."""
        now = self._clock.monotonic()
        if self._pending is None or now - self._hs_quiet >= self.retry_s:
            return self.handshake()
        if now - self._hs_quiet < self.poke_s or self._hs_pokes >= 2:
            return []
        self._hs_pokes += 1
        self._hs_quiet = now
        self.repairs["poke_sent"] += 1
        poke = repair_frame(
            Op.POKE, self._hs_transfer, (0, 0), 0, None,
            sysid=self.sender.sysid, compid=self.sender.compid,
        )  # fmt: skip
        return self._air([poke], "repair")

    def from_air(self, raw: bytes) -> Output:
        """One frame from the air: HS2, telemetry, a repair request, or the vehicle's hint."""
        frame = _parse(raw)
        if frame.msgid == MSG_STATUS:  # unauthenticated: heeded only when the vehicle is silent
            silent = self._clock.monotonic() - self._heard >= self.retry_s
            hinted = read_status(frame) == STATUS_NO_SESSION and silent
            return Output(air=self._retry() if hinted else [])
        if frame.msgid == MSG_REPAIR:
            return self._repair(parse_repair(frame))
        keys = [chunk_key(self.session.recv_key)] if self.session is not None else []
        chunk = parse_chunk(frame)
        done = self._feed(chunk, keys)
        if not isinstance(done, tuple):
            return done or Output()
        kind, blob = done
        if kind is ChunkKind.HS2:
            return self._finish(blob)
        if kind not in (ChunkKind.FRAME, ChunkKind.FRAME_CHUNKED) or self.session is None:
            raise UnknownSessionError(f"{kind.name} blob with no session to take it")
        opened = open_compact(blob, [self.session], Direction.R2I, self.session)
        self._reassembler.opened(chunk, keys[0])
        self._heard = self._clock.monotonic()
        inner, bound = unbind_ack(opened.payload)
        plain = plain_frame(inner)
        if not self._hold_ack(plain, bound):  # a copy of an ACK passed on, or a stale one
            return Output(authenticated=True)
        return Output(local=[plain], authenticated=True)

    def _repair(self, repair: Repair) -> Output:
        """A NACK for one of our transfers; a NACK for the pending HS1 (unauthenticated,
        module :mod:`.repair`, unless a session was live when it left: a rekey's are MACed
        in that session, so nobody can make it resend the HS1 for free) also restarts its
        timer.  A POKE from the vehicle end is its
        answer "never delivered" to ours (:meth:`_undelivered`)."""
        if repair.target != (self.sender.sysid, self.sender.compid):
            return Output()
        if repair.op is Op.POKE:
            return self._undelivered(repair)
        handshake = self._pending is not None and repair.transfer == self._hs_transfer
        if not repair.signed and (not handshake or self._hs_keyed):
            self.repairs["ignored"] += 1
            return Output()
        frames = self._resend(repair)
        if handshake and frames:
            self._hs_quiet = self._clock.monotonic() + self._airtime_s(frames)
        return Output(air=frames)

    def _undelivered(self, repair: Repair) -> Output:
        """The vehicle end's answer to our POKE: that transfer never opened there and never
        can (a later one did).  Believed once, for the try whose POKE carried that nonce
        (a replay of it finds the nonce spent): the command is sealed anew, whole."""
        attempt = next((t for t in self._tries.values() if t.transfer == repair.transfer), None)
        session = self.session
        if attempt is None or attempt.nonce != repair.missing or attempt.session is not session:
            self.repairs["ignored"] += 1
            return Output()
        repair.verify([repair_key(attempt.session.recv_key)])
        self.repairs["undelivered"] += 1
        self._sent.forget(attempt.transfer)
        air = self._seal(attempt.session, inner_of(_parse(attempt.raw)), Purpose.COMMAND)
        attempt.transfer, attempt.nonce = self.sender.transfer, 0
        attempt.due = self._clock.monotonic() + self._airtime_s(air)
        return Output(air=air)

    def _hold_ack(self, plain: bytes, bound: int | None) -> bool:
        """A final COMMAND_ACK the vehicle end bound to a command transfer (sealed with it)
        answers the try of that transfer, and only that one: a GCS retry of it from now
        on is answered with it (within ``retry_window_s``).  False (counted) for a copy
        of an ACK already passed on (the vehicle end sends each twice, and answers POKEs)
        and for a bound ACK whose try is gone: neither may reach a GCS that waits for
        another command's ACK (MAVLink names only the command number)."""
        frame = parse_frame(plain)
        if frame.msgid != dialect.MAVLINK_MSG_ID_COMMAND_ACK:
            return True
        now = self._clock.monotonic()
        if self._last_ack == plain and now - self._last_ack_at < self.retry_window_s:
            self.repairs["ack_duplicate"] += 1
            return False
        if bound is None:  # a command from elsewhere (the vehicle end holds none for it)
            self._last_ack, self._last_ack_at = plain, now
            return True
        attempt = next((t for t in self._tries.values() if t.transfer == bound), None)
        if attempt is None or attempt.ack is not None:
            self.repairs["ack_duplicate" if attempt else "ack_stale"] += 1
            return False
        self._last_ack, self._last_ack_at = plain, now
        if frame.payload[2:3] != bytes([IN_PROGRESS]):
            attempt.ack = plain
            self._sent.forget(attempt.transfer)
        return True

    def _finish(self, hs2: bytes) -> Output:
        if self._pending is None:
            if hs2 == self._hs2:  # the vehicle end answered a POKE that crossed the HS2
                self.reassembly.duplicates += 1
                return Output()
            raise UnknownSessionError("HS2 with no handshake in progress")
        self.session = self.initiator.finish(self._pending[0], hs2)
        self.handshakes["completed"] += 1
        self._sent.forget(self._hs_transfer)
        self._pending, self._heard, self._hs2 = None, self._clock.monotonic(), hs2
        self._epoch = self._heard
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


_T = TypeVar("_T")


def _remember(
    table: OrderedDict[tuple[int, int, int], _T], key: tuple[int, int, int], value: _T
) -> None:
    """Hold ``value`` under ``key``, the oldest of 16 forgotten."""
    table[key] = value
    while len(table) > 16:
        table.popitem(last=False)


@dataclass
class _Held:
    """A command the vehicle end delivered, and the COMMAND_ACK its flight controller gave."""

    command: int
    ack: bytes | None = None

    @property
    def final(self) -> bool:
        """Whether its flight controller gave a final COMMAND_ACK (not IN_PROGRESS)."""
        return self.ack is not None and self.ack[12:13] != bytes([IN_PROGRESS])


class VehicleEnd(RepairingEnd):
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
        gap_s: float = 0.25,
        max_age_s: float = 10.0,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(system_id, component_id, gap_s, clock)
        self.responder = responder
        self.max_age_s = max_age_s  # a command older than this is refused (module docstring)
        self._epochs: dict[bytes, float] = {}  # session id -> when its HS2 left
        self.silence_s = silence_s
        self.signed = signed  # messages delivered only from a command (ML-DSA-87) frame
        self.hint_interval_s = hint_interval_s
        self._sessions: deque[Session] = deque(maxlen=responder.max_sessions)
        self.current: Session | None = None  # the newest session that authenticated
        self._hinted = float("-inf")
        self._heard = float("-inf")  # when an authenticated blob last came from the ground
        # what the ground end may ask for again: HS2s by HS1 transfer, ACKs by command transfer
        self._hs2: OrderedDict[tuple[int, int, int], list[bytes]] = OrderedDict()
        self._answers: OrderedDict[tuple[int, int, int], _Held] = OrderedDict()
        self._unsigned = TokenBucket(2.0, self._clock)  # answers to unauthenticated POKEs
        self._answered: OrderedDict[tuple[int, int, int], int] = OrderedDict()  # times, bounded

    def _sessions_held(self) -> list[Session]:
        return list(self._sessions)

    def _handshake_key(self) -> bytes | None:
        """A handshake's NACKs are MACed in the current session (a rekey's HS1): the ground
        end heeds an unsigned one only when it had no live session."""
        return None if self.current is None else repair_key(self.current.send_key)

    def from_air(self, raw: bytes) -> Output:
        """One frame from the air: HS1 (answered with HS2), a session frame for the FC, or a
        repair request."""
        frame = _parse(raw)
        if frame.msgid == MSG_REPAIR:
            return self._repair(parse_repair(frame))
        keys = [chunk_key(s.recv_key) for s in self._sessions]
        try:
            chunk = parse_chunk(frame)
            done = self._feed(chunk, keys)
        except SignatureInvalidError:
            if keys:
                raise
            raise UnknownSessionError("a session frame, and no live session here") from None
        if not isinstance(done, tuple):
            return done or Output()
        kind, blob = done
        if kind is ChunkKind.HS1:
            return self._accept(chunk, blob)
        if kind is ChunkKind.HS2:
            raise InvalidFrameError("HS2 travels to the ground end")
        self._require_signature(blob)
        opened = open_compact(blob, self._sessions, Direction.I2R, self.responder)
        session = next(s for s in self._sessions if s.session_id == opened.session_id)
        self._reassembler.opened(chunk, chunk_key(session.recv_key))
        self._supersede(session)
        self.current, self._heard = session, self._clock.monotonic()
        command = opened.purpose is Purpose.COMMAND
        inner = self._fresh(opened.payload, session) if command else opened.payload
        plain = plain_frame(inner)
        if int.from_bytes(opened.payload[3:6], "little") in RETRIED:
            _remember(self._answers, chunk.key, _Held(command_of(_parse(plain))))
        return Output(local=[plain], authenticated=True)

    def _fresh(self, payload: bytes, session: Session) -> bytes:
        """A command's inner, its age stamp checked (module docstring): an older command is
        refused (``MESSAGE_STALE``, counted) after it opened, so it is spent as well."""
        if len(payload) < _STAMP.size + _INNER_HEAD:
            raise InvalidFrameError("command frame too short for its age stamp")
        (sent_ms,) = _STAMP.unpack_from(payload, len(payload) - _STAMP.size)
        epoch = self._epochs.get(session.session_id, float("-inf"))
        age = self._clock.monotonic() - epoch - sent_ms / 1000
        if age > self.max_age_s:
            self.drops["STALE"] += 1
            raise MessageStaleError(f"command sealed {age:.1f} s ago (at most {self.max_age_s})")
        return payload[: -_STAMP.size]

    def _accept(self, chunk: Chunk, hs1: bytes) -> Output:
        handles = {s.session_id[-1] for s in self._sessions}
        self.handshakes["started"] += 1
        try:
            session, hs2 = self.responder.accept_handshake(hs1, lambda sid: sid[-1] in handles)
        except ReplayAttackError:
            self.handshakes["failed"] += 1
            raise
        self.handshakes["completed"] += 1
        self._sessions.append(session)
        self.current, self._heard = session, self._clock.monotonic()
        held = {s.session_id for s in self._sessions}
        self._epochs = {k: v for k, v in self._epochs.items() if k in held}
        self._epochs[session.session_id] = self._heard
        frames = self.sender.frames(hs2, ChunkKind.HS2)
        _remember(self._hs2, chunk.key, frames)
        return Output(air=self._air(frames), authenticated=True)

    def _repair(self, repair: Repair) -> Output:
        """A NACK for our own (telemetry) transfers, or the ground end's POKE: answered
        with what is held for that transfer (HS2, COMMAND_ACK), or with a NACK."""
        if repair.op is Op.NACK:
            if repair.target != (self.sender.sysid, self.sender.compid) or not repair.signed:
                return Output()
            return Output(air=self._resend(repair))
        if repair.signed:
            return Output(air=self._poked(repair))
        answer = self._poked_unsigned(repair) if self._unsigned.take() else []
        return Output(air=answer, reply=True)

    def _poked_unsigned(self, repair: Repair) -> list[bytes]:
        """A handshake's POKE: the HS2 held for that HS1, or a NACK for its chunks (bounded,
        rate-limited: nothing authenticates it)."""
        at = (repair.sysid, repair.compid, repair.transfer)
        held = self._hs2.get(at)
        if held is not None:
            return self._answer(at, lambda: held)
        found = self._reassembler.lookup(at[:2], at[2])
        if found is not None and found[0] is not ChunkKind.HS1:
            return []
        return self._nack(at, None, EVERYTHING if found is None else bitmap(found[2]))

    def _poked(self, repair: Repair) -> list[bytes]:
        """A POKE in a session (a GCS retry): the held COMMAND_ACK again, or a NACK for the
        chunks still missing (all of them, for a fresh transfer never seen)."""
        key = repair.verify([repair_key(s.recv_key) for s in self._sessions])
        session = next(s for s in self._sessions if repair_key(s.recv_key) == key)
        at = (repair.sysid, repair.compid, repair.transfer)
        answer = self._answers.get(at)
        if answer is not None:
            ack = answer.ack
            if ack is None:
                return []
            return self._answer(at, lambda: self._seal(session, ack, at[2]))
        ckey = chunk_key(session.recv_key)
        found = self._reassembler.lookup(at[:2], at[2])
        if found is not None:
            return self._nack(at, ckey, bitmap(found[2]))
        if self._reassembler.completed(at[:2], at[2]):
            return []
        if self._reassembler.is_fresh(at[:2], at[2], ckey):
            return self._nack(at, ckey, EVERYTHING)
        # never opened, and never can (a later transfer did): "not delivered", echoing the
        # POKE's nonce so that only the try that asked believes it
        mac = repair_key(session.send_key)
        undelivered = repair_frame(
            Op.POKE, at[2], at[:2], repair.missing, mac,
            sysid=self.sender.sysid, compid=self.sender.compid,
        )  # fmt: skip
        return self._answer(at, lambda: [undelivered])

    def _answer(self, at: tuple[int, int, int], frames: Callable[[], list[bytes]]) -> list[bytes]:
        """A held answer again, at most ``MAX_ANSWERS`` times per transfer."""
        _remember(self._answered, at, self._answered.get(at, 0) + 1)
        if self._answered[at] > MAX_ANSWERS:
            return []
        self.repairs["answered"] += 1
        return self._air(frames(), "repair")

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
        frame = status_frame(STATUS_NO_SESSION, self.sender.sysid, self.sender.compid)
        return self._air([frame], "repair")

    def from_local(self, raw: bytes) -> list[bytes]:
        """:meth:`handle_local`'s air frames."""
        return self.handle_local(raw).air

    def handle_local(self, raw: bytes) -> Output:
        """Wrap one telemetry frame from the flight controller; with no session it is
        dropped and counted (:attr:`drops`): the flight controller streams long before
        the ground end connects, which is no fault.  A COMMAND_ACK is also held for the
        command it answers, for the ground end's POKE (a GCS retry), and its first goes
        out twice (under two counters; the ground end passes one on): one lost costs the
        ground station no retry, for some 60 bytes."""
        frame = _parse(raw)
        if self.current is None:
            self.drops["NO_SESSION"] += 1
            return Output()
        copies, bound = 1, None
        if frame.msgid == dialect.MAVLINK_MSG_ID_COMMAND_ACK:
            bound = self._held_for(command_of(frame))
            if bound is not None:
                held = self._answers[bound]
                copies += held.ack is None
                held.ack = raw
        transfer = None if bound is None else bound[2]
        air = self._air(self._seal(self.current, raw, transfer))
        if copies > 1:
            air += self._air(self._seal(self.current, raw, transfer), "repair")
        return Output(air=air)

    def _held_for(self, command: int) -> tuple[int, int, int] | None:
        """The delivered transfer a COMMAND_ACK for ``command`` answers: the oldest one not
        finally answered (a flight controller answers in order), else the newest."""
        held = [(k, h) for k, h in self._answers.items() if h.command == command]
        waiting = [k for k, h in held if not h.final]
        return waiting[0] if waiting else held[-1][0] if held else None

    def _seal(self, session: Session, raw: bytes, bound: int | None = None) -> list[bytes]:
        """Seal a telemetry frame; a COMMAND_ACK bound to the transfer it answers."""
        inner = inner_of(_parse(raw))
        if bound is not None:
            inner = bind_ack(inner, bound)
        blob = compact(session.seal(inner, Purpose.DATA))
        frames = self.sender.frames(blob, ChunkKind.FRAME, chunk_key(session.send_key))
        self._sent.add(self.sender.transfer, frames, repair_key(session.recv_key))
        return frames

    def tick(self) -> list[bytes]:
        """What time alone calls for: ask for chunks of transfers that went quiet (the
        ground end opens sessions)."""
        return self._stale_nacks()

    @property
    def live(self) -> Session | None:
        """The current session, while the ground end was heard within ``silence_s``."""
        silent = self._clock.monotonic() - self._heard >= self.silence_s
        return None if silent else self.current
