"""The vehicle end of a PQ link (the responder), next to the autopilot.

Theory of operation
-------------------
Sans-I/O: bytes and a time in, frames out; :mod:`.link` drives it and calls ``tick``.
It answers an HS1 with an HS2 (held, so that a POKE for a lost one is answered again),
opens session frames for the flight controller, repairs transfers (:mod:`.repair`) and
hints its presence every ``hint_interval_s``.  :attr:`VehicleEnd.live` is the newest
session that authenticated while something authenticated was heard from the ground end
within ``silence_s``; handshakes, drops and repairs are counted.

A GCS retry (:mod:`.ground`) arrives as an authenticated POKE naming a transfer: for a
transfer that opened, the vehicle end answers with its held ``COMMAND_ACK`` sealed anew
(at most ``MAX_ANSWERS`` times) bound to that transfer (:func:`~.repair.bind_ack`) and
delivers nothing again; for one that never opened and never can (a later one did), "not
delivered" echoing the nonce.  A command repeated on purpose within the ground end's
retry window is answered, not executed: repeat it after the window.

An HS1 refused after it parsed (its signature, its identity, its timestamp: the codes of
:data:`~.wire.REFUSALS`) is answered with one ``PQ_REFUSAL`` per HS1 (by hash), MACed
under that HS1's refusal key (:func:`~antireplay.pq.session.refusal_key`: the vehicle's
ML-KEM key, so the ground end can verify it against the key it pins, and it fits one
frame where an ML-DSA-87 signature would take twenty), and only within an airtime budget
(:data:`~.wire.HANDSHAKE_SHARE` of ``air_bps``): a flood of bad HS1s is no amplifier.
The budget is shared by claimed identity: half for the vehicle's known peers (each its
own part), half for every other claim, so junk claiming unknown names cannot starve a
known identity's refusal (junk claiming a known name still can: it spends that name's
part).  A refusal the budget withheld is not recorded as answered: the same HS1 again,
or its POKE, is answered once the budget allows.  The link sends it
(:meth:`VehicleEnd.answered`) as it sends the ``PQ_STATUS`` hint; a POKE for a refused
HS1 gets no NACK (sent again, it would be refused again).

A command's age stamp (:data:`~.wire.AGEAGE_STAMP`) says when the ground end sealed it,
in milliseconds since its session came up there.  The vehicle end refuses
(``MESSAGE_STALE``, counted in ``drops``) a command older than ``max_age_s`` by its own
time since it sent that HS2.  No clocks are compared: each end measures from its side of
one event, and the vehicle's side comes first (the HS2 leaves before it arrives), so the
vehicle reckons a command older than it is, never younger: a command withheld on the air
and released later is refused however the attacker times it.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

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
)
from antireplay.mavlink.pq.wire import (
    _COMPACT,
    _INNER_HEAD,
    AGE_STAMP,
    MSG_REPAIR,
    REFUSAL_OF,
    SIGNED_MESSAGES,
    STATUS_NO_SESSION,
    ChunkKind,
    compact,
    handshake_ttl_s,
    inner_of,
    open_compact,
    plain_frame,
    refusal_frame,
    share_rate,
    status_frame,
)
from antireplay.pq.session import (
    Direction,
    Purpose,
    Responder,
    Session,
)

_T = TypeVar("_T")
_REFUSAL_AIR = 12 + 93 + 2  # a PQ_REFUSAL's air bytes at most


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
        air_bps: int | None = None,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(system_id, component_id, gap_s, clock)
        if air_bps is not None and air_bps <= 0:
            raise ValueError(f"air_bps must be positive (baud), or None for unknown: {air_bps}")
        self._reassembler.handshake_timeout_s = handshake_ttl_s(air_bps)  # slow radios
        # refusals: their share of the air, by claimed identity, one per HS1 (by hash)
        self._share = share_rate(air_bps)
        self._refusal_budgets: dict[str, TokenBucket] = {}
        self._refused: OrderedDict[bytes, None] = OrderedDict()
        # transfers refused: the HS1 and why while its refusal is withheld (None: sent)
        self._refused_at: OrderedDict[
            tuple[int, int, int], tuple[bytes, ReplayAttackError] | None
        ] = OrderedDict()
        self._refusal_out: list[bytes] = []  # a refusal the link sends with the error
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
        if len(payload) < AGE_STAMP.size + _INNER_HEAD:
            raise InvalidFrameError("command frame too short for its age stamp")
        (sent_ms,) = AGE_STAMP.unpack_from(payload, len(payload) - AGE_STAMP.size)
        epoch = self._epochs.get(session.session_id, float("-inf"))
        age = self._clock.monotonic() - epoch - sent_ms / 1000
        if age > self.max_age_s:
            self.drops["STALE"] += 1
            raise MessageStaleError(f"command sealed {age:.1f} s ago (at most {self.max_age_s})")
        return payload[: -AGE_STAMP.size]

    def _accept(self, chunk: Chunk, hs1: bytes) -> Output:
        handles = {s.session_id[-1] for s in self._sessions}
        self.handshakes["started"] += 1
        try:
            session, hs2 = self.responder.accept_handshake(hs1, lambda sid: sid[-1] in handles)
        except ReplayAttackError as exc:
            self.handshakes["failed"] += 1
            self._refusal_out = self._refusal(chunk.key, hs1, exc)
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

    def _refusal(self, at: tuple[int, int, int], hs1: bytes, exc: ReplayAttackError) -> list[bytes]:
        """A ``PQ_REFUSAL`` of ``hs1`` (module docstring): once per HS1, within budget."""
        number = REFUSAL_OF.get(exc.code)
        if number is None:
            return []  # a replay, a malformed HS1: nothing its sender could act on
        digest = hashlib.sha256(hs1).digest()
        if digest in self._refused:
            self.refusals["withheld"] += 1
            return []
        if not self._refusal_budget(hs1).take(_REFUSAL_AIR):
            self.refusals["withheld"] += 1
            _remember(self._refused_at, at, (hs1, exc))  # answered when poked again
            return []
        _remember(self._refused_at, at, None)  # a POKE for it gets no NACK
        self._refused[digest] = None
        while len(self._refused) > 64:
            self._refused.popitem(last=False)
        key = self.responder.refusal_key(hs1)  # after the budget: decapsulation costs
        if key is None:
            return []
        frame = refusal_frame(
            hs1, key, transfer=at[2], target=at[:2], code=number,
            reason=exc.reason, sysid=self.sender.sysid, compid=self.sender.compid,
        )  # fmt: skip
        self.refusals["sent"] += 1
        return self._air([frame], "repair")

    def _refusal_budget(self, hs1: bytes) -> TokenBucket:
        """The part of the refusal budget the identity ``hs1`` claims draws on (module
        docstring): half the share split among the known peers, half for the rest."""
        claimed = self.responder.claimed(hs1)
        peers = self.responder.peers
        name = claimed if claimed in peers else ""
        budget = self._refusal_budgets.get(name)
        if budget is None:
            rate = self._share / 2 / (max(1, len(peers)) if name else 1)
            budget = TokenBucket(rate, self._clock, burst=2 * _REFUSAL_AIR)
            self._refusal_budgets[name] = budget
        return budget

    def answered(self) -> list[bytes]:
        """The refusal of the HS1 just refused, once (the link sends it to its sender)."""
        out, self._refusal_out = self._refusal_out, []
        return out

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
        """A handshake's POKE: the HS2 held for that HS1, nothing for an HS1 refused, or a
        NACK for its chunks (bounded, rate-limited: nothing authenticates it)."""
        at = (repair.sysid, repair.compid, repair.transfer)
        held = self._hs2.get(at)
        if held is not None:
            return self._answer(at, lambda: held)
        if at in self._refused_at:  # refused whole: resending it would change nothing
            withheld = self._refused_at[at]
            if withheld is None:
                return []
            return self._refusal(at, *withheld)  # its refusal, if the budget allows now
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
