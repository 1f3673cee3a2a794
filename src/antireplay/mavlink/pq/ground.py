"""The ground end of a PQ link (the initiator), next to the ground station.

Theory of operation
-------------------
Sans-I/O: bytes and a time in, frames out; :mod:`.link` drives it and calls ``tick`` on a
timer, so a quiet transfer is repaired (:mod:`.repair`) and a lost handshake is poked,
then retried, whether or not local traffic arrives: the HS1 is POKEd ``poke_s`` after its
chunks left (by ``air_bps``) or were last repaired (twice at most), and a new one starts
only after the backoff, so repairs never race a new HS1.  Failing handshakes draw on one
airtime budget (:mod:`.budget`).  :attr:`GroundEnd.live` is the session while something
authenticated came from the vehicle end within ``silence_s``.

A GCS retry (:meth:`GroundEnd.handle_local`), an identical command within ``retry_window_s``
of the first try (a fixed window), asks the vehicle end by an authenticated POKE naming
that transfer (and a fresh nonce) what it holds (:mod:`.vehicle`).  Every ACK travels
bound to the transfer it answers (:func:`~.repair.bind_ack`): a try gets only its own
transfer's ACK, none twice, so a replayed POKE or another command with the same number
never tells a GCS that its command was accepted.  A "not delivered" answer echoing the
nonce makes it send that command anew, whole.

A verified ``PQ_REFUSAL`` for the pending HS1 ends that attempt and is told once; a forged
one, or another attempt's, changes nothing.  A command carries, sealed with it, its age
stamp (:data:`~.wire.AGE_STAMP`: ms since its session came up here); the vehicle judges it.
"""

from __future__ import annotations

import random
import secrets
from collections import OrderedDict, deque
from dataclasses import dataclass

from cryptography.hazmat.primitives.asymmetric import mlkem, x25519
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.core.clock import Clock
from antireplay.core.errors import (
    ReplayDetectedError,
    SignatureInvalidError,
    UnknownSessionError,
)
from antireplay.mavlink.codec import Frame, parse_frame
from antireplay.mavlink.pq.budget import HandshakeBudget
from antireplay.mavlink.pq.chunks import (
    chunk_key,
    parse_chunk,
)
from antireplay.mavlink.pq.repair import (
    IN_PROGRESS,
    Op,
    Output,
    Repair,
    RepairingEnd,
    _parse,
    command_of,
    parse_repair,
    repair_frame,
    repair_key,
    retry_key,
    unbind_ack,
)
from antireplay.mavlink.pq.wire import (
    AGE_STAMP,
    LINE_BITS,
    MAX_BACKOFF_S,
    MSG_REFUSAL,
    MSG_REPAIR,
    MSG_STATUS,
    REKEY_TRANSFERS,
    SIGNED_MESSAGES,
    STATUS_NO_SESSION,
    TRANSFER_LIMIT,
    ChunkKind,
    Refusal,
    compact,
    handshake_ttl_s,
    inner_of,
    open_compact,
    parse_refusal,
    plain_frame,
    read_status,
)
from antireplay.pq.session import (
    Direction,
    Initiator,
    Purpose,
    Session,
)

STALE_SLACK_S = 2.0  # clock agreement slack (:meth:`~.wire.Refusal.explained_after`)


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
        max_backoff_s: float = MAX_BACKOFF_S,
        rng: random.Random | None = None,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(system_id, component_id, gap_s, clock)
        #: Air a failing handshake may take, and its backoff (:mod:`.budget`).
        self.budget = HandshakeBudget(self._clock, retry_s, max_backoff_s, air_bps, rng)
        self._hs_refused = False  # the pending HS1 was refused (a verified PQ_REFUSAL)
        self._told: str | None = None  # the refusal last told (once until a session)
        self.initiator, self.responder_key = initiator, responder_key
        self.hybrid = hybrid  # the vehicle's static X25519 key: hybrid handshakes
        self.signed, self.retry_s, self.silence_s = signed, retry_s, silence_s
        self.poke_s, self.retry_window_s, self.air_bps = poke_s, retry_window_s, air_bps
        self._proven = False  # this session carried authenticated vehicle traffic
        self._reassembler.handshake_timeout_s = handshake_ttl_s(air_bps)  # slow radios
        self._deferred: Repair | None = None  # a NACK that came while the HS1 was leaving
        self._first_transfer = 0  # the sender's transfer number when the session began
        self.session: Session | None = None
        self._pending: tuple[bytes, float] | None = None  # HS1 and when it left
        self._hs_transfer, self._hs_quiet, self._hs_pokes, self._hs_leaves = 0, 0.0, 0, 0.0
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
        self._hs_refused = False
        hs1 = self.initiator.start(self.responder_key, self.hybrid)
        now = self._clock.monotonic()
        self._pending = (hs1, now)
        self._hs_transfer = secrets.randbelow(0x10000)
        frames = self.sender.frames(hs1, ChunkKind.HS1, transfer=self._hs_transfer)
        live = self.live  # a rekey: its NACKs must come MACed in the live session
        self._hs_keyed = live is not None
        key = None if live is None else repair_key(live.recv_key)
        self._sent.add(self._hs_transfer, frames, key, handshake_ttl_s(self.air_bps))
        self._deferred = None  # a NACK for the last attempt is no NACK for this one
        self._hs_quiet, self._hs_pokes = now + self._airtime_s(frames), 0
        self._hs_leaves = self._hs_quiet  # when its chunks have all left (by air_bps)
        self.budget.attempt(sum(map(len, frames)))
        return self._air(frames)

    @property
    def next_attempt_at(self) -> float:
        """When the pending handshake may be superseded (monotonic; budget aside)."""
        return self._hs_quiet + self.budget.backoff

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
        out = self._stale_nacks() + self._deferred_repair()
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
        if silent:
            return self._retry()
        if session.needs_rekey or self._transfers_used() >= REKEY_TRANSFERS:
            return self._retry(due=True)  # traffic's rekey: its HS1 is charged, never held
        return []

    def _transfers_used(self) -> int:
        return (self.sender.transfer - self._first_transfer) & 0xFFFF

    def _seal(self, session: Session, inner: bytes, purpose: Purpose) -> list[bytes]:
        """Seal a frame; a command with its age stamp (module docstring)."""
        if purpose is Purpose.COMMAND:
            age_ms = int(max(0.0, self._clock.monotonic() - self._epoch) * 1000)
            inner += AGE_STAMP.pack(min(age_ms, 0xFFFFFFFF))
        blob = compact(session.seal(inner, purpose))
        frames = self.sender.frames(blob, ChunkKind.FRAME, chunk_key(session.send_key))
        self._sent.add(self.sender.transfer, frames, repair_key(session.recv_key))
        return self._air(frames)

    def _retry(self, due: bool = False) -> list[bytes]:
        """The pending handshake's timer: quiet for ``poke_s`` after its chunks left (by
        ``air_bps``) or were last repaired, a POKE (twice at most: the HS2 may be lost, or
        the tail of HS1; none after a refusal); quiet for the backoff (``retry_s`` first,
        then doubling), a new handshake, once the airtime budget holds one (``due``: a
        live session's rekey, which traffic itself paces, waits for none)."""
        now = self._clock.monotonic()
        if self._pending is None or now >= self.next_attempt_at:
            if not due and not self.budget.holds_hs1():
                return []
            return self.handshake()
        if now - self._hs_quiet < self.poke_s or self._hs_pokes >= 2 or self._hs_refused:
            return []
        if not self.budget.take_poke():
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
        if frame.msgid in (MSG_STATUS, MSG_REPAIR, MSG_REFUSAL):
            return self._control(frame)
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
        if not self._proven:  # the session works: no misconfigured end to hold back
            self._proven, self._told = True, None
            self.budget.proven()
        inner, bound = unbind_ack(opened.payload)
        plain = plain_frame(inner)
        if not self._hold_ack(plain, bound):  # a copy of an ACK passed on, or a stale one
            return Output(authenticated=True)
        return Output(local=[plain], authenticated=True)

    def _control(self, frame: Frame) -> Output:
        """The vehicle end's hint (unauthenticated: heeded only when it is silent), a repair
        request, or its refusal of our handshake."""
        if frame.msgid == MSG_REPAIR:
            return self._repair(parse_repair(frame))
        if frame.msgid == MSG_REFUSAL:
            return self._refused(parse_refusal(frame))
        silent = self._clock.monotonic() - self._heard >= self.retry_s
        hinted = read_status(frame) == STATUS_NO_SESSION and silent
        return Output(air=self._retry() if hinted else [])

    def _repair(self, repair: Repair) -> Output:
        """A NACK for one of our transfers; a NACK for the pending HS1 (unauthenticated,
        module :mod:`.repair`, unless a session was live when it left: a rekey's are MACed
        in that session, so nobody can make it resend the HS1 for free) also restarts its
        timer, but an unsigned one resends each chunk once per attempt and never delays the
        next attempt; one that comes while its chunks are still leaving (by ``air_bps``)
        asks for chunks on their way, and is ignored.  Its resends draw on the handshake
        budget.
        A POKE from the vehicle end is its answer "never delivered" to ours
        (:meth:`_undelivered`)."""
        if repair.target != (self.sender.sysid, self.sender.compid):
            return Output()
        if repair.op is Op.POKE:
            return self._undelivered(repair)
        handshake = self._pending is not None and repair.transfer == self._hs_transfer
        if not repair.signed and (not handshake or self._hs_keyed):
            self.repairs["ignored"] += 1
            return Output()
        if handshake and self._clock.monotonic() < self._hs_leaves:  # chunks on their way
            self._deferred = repair  # honoured once they left (:meth:`tick`)
            self.repairs["deferred"] += 1
            return Output()
        frames = self._resend(repair, self.budget.affords(repair.signed) if handshake else None)
        if handshake and frames:
            now = self._clock.monotonic()
            self._hs_leaves = max(self._hs_leaves, now + self._airtime_s(frames))
        if handshake and frames and repair.signed:
            self._hs_quiet = self._clock.monotonic() + self._airtime_s(frames)
        return Output(air=frames)

    def _deferred_repair(self) -> list[bytes]:
        """The NACK that came while the pending HS1 was leaving, once it has left."""
        deferred = self._deferred
        if deferred is None or self._clock.monotonic() < self._hs_leaves:
            return []
        self._deferred = None
        if self._pending is None or deferred.transfer != self._hs_transfer:
            return []
        return self._repair(deferred).air

    def _refused(self, refusal: Refusal) -> Output:
        """The vehicle end's ``PQ_REFUSAL``: believed only for the pending HS1 (its hash,
        its transfer, a MAC under that HS1's refusal key), then that attempt is over and
        the reason told once; anything else raises, counted (module docstring)."""
        if refusal.target != (self.sender.sysid, self.sender.compid):
            self.refusals["elsewhere"] += 1  # another ground end's (a shared air)
            return Output()
        pending, left = self._pending or (None, 0.0)
        if pending is None or self._hs_refused or not refusal.names(pending):
            self.refusals["stale"] += 1
            raise ReplayDetectedError("PQ_REFUSAL of no pending handshake (another attempt's)")
        key = self.initiator.refusal_key(pending)
        if key is None or refusal.transfer != self._hs_transfer or not refusal.verify(pending, key):
            self.refusals["forged"] += 1
            raise SignatureInvalidError("PQ_REFUSAL MAC does not verify")
        self.refusals["verified"] += 1
        self.handshakes["refused"] += 1
        self._hs_refused = True
        self._sent.forget(self._hs_transfer)
        held, slack = self._clock.monotonic() - left, STALE_SLACK_S + self._airtime_s([pending])
        told = f"vehicle refused the handshake: {refusal.explained_after(held, slack)}"
        if told == self._told:
            return Output()
        self._told = told
        return Output(notice=told)

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
        self._proven = False  # the budget and backoff reset once vehicle traffic comes
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
