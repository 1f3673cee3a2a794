"""Repairs: ``PQ_REPAIR`` frames, the sender's copy of what it sent, and command retries.

Theory of operation
-------------------
A lost chunk costs that chunk, not its blob.  Parity (:mod:`.chunks`) absorbs one loss
per parity group without a round trip; beyond that the receiver sends a **NACK**
naming the fewest missing indices (:meth:`~.chunks.Reassembler.missing`), as soon as
the transfer's last chunk arrives incomplete, or ``gap_s`` after anything last came
for it (its tail lost, or a repair), at most ``MAX_NACKS`` times.  The sender keeps
the frames of its last few multi-chunk transfers (:class:`SendCache`, bounded in
number and age) and resends exactly the requested ones, the same bytes: each still
carries its chunk MAC, and the receiver de-duplicates.  A **POKE** goes the other way:
the sender of a transfer asks where it stands (a GCS retry, an unanswered HS1); the
receiver answers with a NACK (incomplete, or never seen: all of it) or, for a blob it
already took, with what it held as the answer (the HS2, a command's ``COMMAND_ACK``).

A repair frame is MACed (:func:`repair_key`, from the sender's data key of the session
the transfer travels in), so one forged in a session is refused
(``SIGNATURE_INVALID``).  One recorded and replayed can only ask again for chunks of a
transfer the sender still holds, within its budget (``RESEND_BUDGET`` times its chunk
count), or a held answer again (at most ``MAX_ANSWERS``): bounded airtime, every
resent chunk de-duplicated or refused as a replay, and no state anywhere changes.
Before a session exists (the handshake) nothing can authenticate a repair: its MAC is
zero, and it can only make the ground end resend chunks of its *pending* HS1 (public
already, within the same budget) or the vehicle end resend an HS2 it holds (public,
at most ``MAX_ANSWERS`` times): the worst it does is what jamming does, spend airtime.
Both ends build on :class:`RepairingEnd` (reassembly that NACKs, the send cache, and the
airtime each end hands out, by kind: :data:`AIR_KINDS`).
"""

from __future__ import annotations

import hmac
import struct
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum

from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import InvalidFrameError, SignatureInvalidError
from antireplay.mavlink.codec import Frame, parse_frame
from antireplay.mavlink.pq.chunks import (
    Chunk,
    ChunkSender,
    PlainFrameError,
    Reassembler,
    ReassemblyStats,
    chunk_key,
)
from antireplay.mavlink.pq.wire import (
    CHUNK_MAC,
    DIALECT,
    MSG_CHUNK,
    MSG_REPAIR,
    ChunkKind,
    _payload_of,
    pack_v2,
)
from antireplay.pq.session import Session

_REPAIR = struct.Struct("<QHBBB8s")
EVERYTHING = (1 << 64) - 1  # a NACK's bitmap for a transfer the receiver never saw
RESEND_BUDGET = 2  # chunks a sender resends for one transfer, times its chunk count
MAX_ANSWERS = 3  # times a held answer (HS2, COMMAND_ACK) is sent again
_NO_MAC = bytes(CHUNK_MAC)
_CONFIRMATION_AT = 32  # COMMAND_LONG's confirmation byte, which a GCS bumps on a retry


class Op(IntEnum):
    NACK = 1
    POKE = 2


def repair_key(data_key: bytes) -> bytes:
    """The repair-MAC key of a session direction (derived from its data key)."""
    return hmac.digest(data_key, b"antireplay/v1 repair", "sha256")


@dataclass(frozen=True)
class Repair:
    """One ``PQ_REPAIR``, bounds checked (its MAC not yet checked)."""

    sysid: int
    compid: int
    op: Op
    transfer: int
    target: tuple[int, int]
    missing: int
    mac: bytes

    def _input(self) -> bytes:
        body = _REPAIR.pack(self.missing, self.transfer, *self.target, self.op, _NO_MAC)
        return bytes([self.sysid, self.compid]) + body[:-CHUNK_MAC]

    @property
    def signed(self) -> bool:
        return self.mac != _NO_MAC

    def verify(self, keys: list[bytes]) -> bytes:
        """The repair key it verifies under; ``SIGNATURE_INVALID`` otherwise."""
        for key in keys:
            if hmac.compare_digest(_mac(key, self._input()), self.mac):
                return key
        raise SignatureInvalidError("repair request MAC does not verify")

    def indices(self, total: int) -> list[int]:
        return [i for i in range(total) if self.missing >> i & 1]


def _mac(key: bytes, data: bytes) -> bytes:
    return hmac.digest(key, data, "sha256")[:CHUNK_MAC]


def repair_frame(
    op: Op,
    transfer: int,
    target: tuple[int, int],
    missing: int,
    key: bytes | None,
    *,
    sysid: int,
    compid: int,
) -> bytes:
    """A ``PQ_REPAIR`` frame, MACed under ``key`` (None: a handshake's, MAC zero)."""
    bits = missing & EVERYTHING
    unsigned = Repair(sysid, compid, op, transfer, target, bits, _NO_MAC)
    mac = _NO_MAC if key is None else _mac(key, unsigned._input())
    payload = _REPAIR.pack(bits, transfer, *target, op, mac)
    crc_extra = DIALECT[MSG_REPAIR][0]
    return pack_v2(MSG_REPAIR, payload, crc_extra, sysid=sysid, compid=compid, seq=0)


def bitmap(indices: list[int]) -> int:
    return sum(1 << i for i in indices)


def parse_repair(frame: Frame) -> Repair:
    """The cheap checks; every failure is a typed INVALID_FRAME."""
    missing, transfer, system, component, op, mac = _REPAIR.unpack(_payload_of(frame))
    if op not in (Op.NACK, Op.POKE):
        raise InvalidFrameError("unknown repair operation")
    return Repair(frame.sysid, frame.compid, Op(op), transfer, (system, component), missing, mac)


@dataclass
class _Sent:
    frames: list[bytes]
    key: bytes | None  # the repair key its NACKs verify under (None: an HS1's)
    born: float
    ttl_s: float
    resent: int = 0


class SendCache:
    """The frames of a sender's last ``max_transfers`` multi-chunk transfers, each for
    ``ttl_s``, resent on request within ``RESEND_BUDGET`` (module docstring)."""

    def __init__(self, *, max_transfers: int = 8, ttl_s: float = 10.0, clock: Clock) -> None:
        self.max_transfers, self.ttl_s = max_transfers, ttl_s
        self._clock = resolve(clock)
        self._sent: OrderedDict[int, _Sent] = OrderedDict()

    def add(
        self, transfer: int, frames: list[bytes], key: bytes | None, ttl_s: float | None = None
    ) -> None:
        """Hold ``frames`` for ``ttl_s`` (this cache's when None: an HS1's is longer)."""
        if len(frames) < 2:
            return
        held = self.ttl_s if ttl_s is None else ttl_s
        self._sent[transfer] = _Sent(frames, key, self._clock.monotonic(), held)
        self._sent.move_to_end(transfer)
        while len(self._sent) > self.max_transfers:
            self._sent.popitem(last=False)

    def holds(self, transfer: int) -> bool:
        return self._live(transfer) is not None

    def forget(self, transfer: int) -> None:
        self._sent.pop(transfer, None)

    def resend(self, repair: Repair) -> list[bytes]:
        """The frames a NACK asks for (authenticated as the transfer was sent), within
        budget; none for a transfer no longer held.  A bad MAC: ``SIGNATURE_INVALID``."""
        sent = self._live(repair.transfer)
        if sent is None:
            return []
        if sent.key is not None:
            repair.verify([sent.key])
        wanted = repair.indices(len(sent.frames))
        room = RESEND_BUDGET * len(sent.frames) - sent.resent
        wanted = wanted[: max(room, 0)]
        sent.resent += len(wanted)
        return [sent.frames[i] for i in wanted]

    def _live(self, transfer: int) -> _Sent | None:
        sent = self._sent.get(transfer)
        if sent is not None and self._clock.monotonic() - sent.born > sent.ttl_s:
            del self._sent[transfer]
            return None
        return sent


RETRIED = frozenset({dialect.MAVLINK_MSG_ID_COMMAND_LONG, dialect.MAVLINK_MSG_ID_COMMAND_INT})


def retry_key(frame: Frame) -> tuple[int, int, int, bytes] | None:
    """What makes two commands one command tried twice: source, message, and the payload
    (target, command, parameters) less COMMAND_LONG's ``confirmation``; None for a
    message that is not a command with an acknowledgement."""
    if frame.msgid not in RETRIED:
        return None
    payload = bytearray(frame.payload.ljust(dialect.mavlink_map[frame.msgid].unpacker.size, b"\0"))
    if frame.msgid == dialect.MAVLINK_MSG_ID_COMMAND_LONG:
        payload[_CONFIRMATION_AT] = 0
    return frame.sysid, frame.compid, frame.msgid, bytes(payload)


def command_of(frame: Frame) -> int:
    """The ``command`` of a COMMAND_LONG, COMMAND_INT or COMMAND_ACK frame."""
    payload = frame.payload.ljust(32, b"\0")
    at = {dialect.MAVLINK_MSG_ID_COMMAND_LONG: 28, dialect.MAVLINK_MSG_ID_COMMAND_INT: 28}
    offset = at.get(frame.msgid, 0)
    return int.from_bytes(payload[offset : offset + 2], "little")


#: A COMMAND_ACK result that is not final: the command is still running.
IN_PROGRESS = dialect.MAV_RESULT_IN_PROGRESS
_ACK_AT = 6  # an inner's payload offset (its head: sysid compid seq msgid[3])
_ACK_FULL = 10  # a COMMAND_ACK's payload with every extension field (MAVLink v2)


def bind_ack(inner: bytes, transfer: int) -> bytes:
    """A COMMAND_ACK's inner bound to the command transfer it answers: its payload padded
    to full length, then the transfer number.  It travels sealed (the binding is
    authenticated with the ACK); no plain COMMAND_ACK payload is that long, so a bound
    one is told from an unbound one by its length alone (:func:`unbind_ack`)."""
    payload = inner[_ACK_AT:].ljust(_ACK_FULL, b"\0")
    return inner[:_ACK_AT] + payload + transfer.to_bytes(2, "little")


def unbind_ack(inner: bytes) -> tuple[bytes, int | None]:
    """The plain inner and the transfer a bound COMMAND_ACK answers (None: not bound)."""
    msgid = int.from_bytes(inner[3:6], "little")
    if msgid != dialect.MAVLINK_MSG_ID_COMMAND_ACK or len(inner) != _ACK_AT + _ACK_FULL + 2:
        return inner, None
    payload = inner[_ACK_AT : _ACK_AT + _ACK_FULL].rstrip(b"\0") or b"\0"
    return inner[:_ACK_AT] + payload, int.from_bytes(inner[-2:], "little")


@dataclass
class Output:
    """What an end wants written: plain frames for its local side, chunks for the air."""

    local: list[bytes] = field(default_factory=list)
    air: list[bytes] = field(default_factory=list)
    #: A blob verified (HS1, HS2, a session frame): its sender may be learned as the air peer.
    authenticated: bool = False
    #: Answer the frame's sender without learning it (a handshake's repair: no session yet
    #: to learn the peer from; a NACK is smaller than what asked for it, nothing amplifies).
    reply: bool = False
    #: Something the operator must hear once (the vehicle end refused our handshake).
    notice: str | None = None


def _parse(raw: bytes) -> Frame:
    frame = parse_frame(raw)
    if frame.version != 2:
        raise PlainFrameError("MAVLink v1 frames are not carried")
    return frame


#: What each air byte an end sends is for (:attr:`RepairingEnd.airtime`).
AIR_KINDS = ("hs", "cmd", "parity", "repair", "passthrough")


def air_kind(raw: bytes) -> str:
    """The kind of an air frame this package made (:data:`AIR_KINDS`)."""
    if raw[7] != MSG_CHUNK & 0xFF:
        return "repair"  # PQ_REPAIR, and the PQ_STATUS hint
    index, count, kind = raw[12], raw[13], ChunkKind(raw[15] & 0x0F)
    if index >= count:
        return "parity"
    if kind in (ChunkKind.HS1, ChunkKind.HS2):
        return "hs"
    return "cmd" if kind is ChunkKind.FRAME_CHUNKED else "passthrough"


class RepairingEnd:
    """What both ends share: reassembly with repair requests, the send cache, airtime."""

    def __init__(self, system_id: int, component_id: int, gap_s: float, clock: Clock | None):
        self.sender = ChunkSender(system_id, component_id)
        self.gap_s = gap_s
        self._clock = resolve(clock)
        self._reassembler = Reassembler(clock=clock)
        self._sent = SendCache(clock=self._clock)
        #: Air bytes this end handed out, by kind (:data:`AIR_KINDS`).
        self.airtime: Counter[str] = Counter()
        #: Repairs: ``nack_sent``, ``poke_sent``, ``resent`` (chunks), ``answered`` (a held
        #: HS2 or COMMAND_ACK again), ``ignored`` (for a transfer no longer held).
        self.repairs: Counter[str] = Counter()
        self.drops: Counter[str] = Counter()
        self.handshakes: Counter[str] = Counter()
        #: A GCS's retries (ground end), by how they were answered: ``poked`` (in flight:
        #: a POKE, no new transfer), ``answered`` (the COMMAND_ACK already seen),
        #: ``sending`` (its chunks still going out), ``queued`` (waiting for a session).
        self.retries: Counter[str] = Counter()
        #: ``PQ_REFUSAL`` s: sent or ``withheld`` (vehicle end: one per HS1, within its
        #: airtime budget); ``verified``, ``forged`` or ``stale`` (another attempt's) at
        #: the ground end.
        self.refusals: Counter[str] = Counter()

    def _air(self, frames: list[bytes], kind: str | None = None) -> list[bytes]:
        for raw in frames:
            self.airtime[kind or air_kind(raw)] += len(raw)
        return frames

    def _sessions_held(self) -> list[Session]:
        raise NotImplementedError

    def _handshake_key(self) -> bytes | None:
        """The repair key a handshake's NACK is MACed under (None: unsigned)."""
        return None

    def _session_of(self, key: bytes | None) -> Session | None:
        """The session whose chunk key (its receive direction) is ``key``."""
        for session in self._sessions_held():
            if key is not None and chunk_key(session.recv_key) == key:
                return session
        return None

    def _nack(self, sender: tuple[int, int, int], key: bytes | None, missing: int) -> list[bytes]:
        """A NACK for transfer ``sender`` (sysid, compid, number), MACed in the session its
        chunks authenticated in (none: a handshake's)."""
        session = self._session_of(key)
        mac = self._handshake_key() if session is None else repair_key(session.send_key)
        if key is not None and session is None:
            return []  # its session is gone: nothing to ask for
        self.repairs["nack_sent"] += 1
        frame = repair_frame(
            Op.NACK, sender[2], sender[:2], missing, mac,
            sysid=self.sender.sysid, compid=self.sender.compid,
        )  # fmt: skip
        return self._air([frame], "repair")

    def _feed(self, chunk: Chunk, keys: list[bytes]) -> tuple[ChunkKind, bytes] | Output | None:
        """Reassemble; an Output carrying a NACK when the transfer's last chunk came and
        it is still incomplete (module :mod:`.repair`)."""
        done = self._reassembler.feed(chunk, keys)
        if done is not None:
            return done
        missing = self._reassembler.missing(chunk)
        if missing and self._reassembler.asked(chunk.key):
            transfer_key = self._reassembler.lookup(chunk.key[:2], chunk.transfer)
            assert transfer_key is not None
            nack = self._nack(chunk.key, transfer_key[1], bitmap(missing))
            return Output(air=nack, reply=transfer_key[1] is None)
        return None

    def _stale_nacks(self) -> list[bytes]:
        out: list[bytes] = []
        for key, _, ckey, missing in self._reassembler.stale(self.gap_s):
            out += self._nack(key, ckey, bitmap(missing))
        return out

    def _resend(self, repair: Repair, afford: Callable[[bytes], bool] | None = None) -> list[bytes]:
        """Answer a NACK from the sent copies (:class:`~.repair.SendCache`); with ``afford``
        (an airtime budget) only the frames it affords, the rest counted ``withheld``."""
        frames = self._sent.resend(repair)
        if afford is not None:
            kept = [raw for raw in frames if afford(raw)]
            self.repairs["withheld"] += len(frames) - len(kept)
            frames = kept
        self.repairs["resent" if frames else "ignored"] += len(frames) or 1
        return self._air(frames, "repair")

    @property
    def reassembly(self) -> ReassemblyStats:
        return self._reassembler.stats

    @property
    def unsent(self) -> int:
        """Local messages that never left (:attr:`drops`, all reasons)."""
        return sum(self.drops.values())
