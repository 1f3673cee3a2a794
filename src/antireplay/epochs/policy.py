"""The epoch rules, sans-I/O: the frame, its keys and what an epoch means against the marks.

Theory of operation
-------------------
A sender seals each announcement (kind 1) or binding ping (kind 2) as ::

    sealed = version u8 | kind u8 | nonce_prefix[8] | epoch u64 (big-endian) | payload | tag[32]
    tag    = HMAC-SHA256(k_kind, payload | nonce_prefix | epoch u64 | version u8 | kind u8)
    k_kind = HKDF-SHA256(ikm=psk, salt="", info="antireplay/v1 epoch " + kind name)

Epochs are wall-anchored nanoseconds, strictly increasing per prefix.  A prefix is random,
or derived from a unique service name; a signer whose stream ran ahead of its clock moves
to the public successor ``SHA-256("antireplay/v1 rotate" | prefix)[:8]``.

:class:`EpochPolicy` holds the marks (a bounded :class:`~antireplay.core.counters.FencedTable`
per kind, with recent (epoch, digest) pairs per prefix) and judges values with a time the
driver passes in: a :class:`Refused` (typed error, and evidence for an authentic frame), or an
:class:`Admission` saying what to persist before :meth:`EpochPolicy.commit` moves a mark.  An
authentic, unseen epoch just below the last (``COLLISION_HORIZON_NS``) means a second sender.

**Freshness challenges.**  A verifier without surviving state refuses all at or below its
restart fence; instead of waiting, it seals a random nonce as a ``CHALLENGE`` (ping key, kind
byte under the MAC) and a signer's ``ANSWER`` binds it to the signer's next (prefix, epoch).
That prefix's epochs above the answered one were sealed after the nonce existed, so
:meth:`EpochPolicy.fence_for` lowers its fence to it; every capture stays at or below.  An
answer must bind one of the last ``OUTSTANDING`` nonces and verify before it is committed.
**Key rotation.**  A :class:`KeyRing` holds the fleet key and, during a rotation, its
successor and the cut-over time: an epoch after the cut-over is sealed with the successor,
and both keys verify until then; a frame the old key seals after the cut-over is refused
(``SIGNATURE_INVALID``, ``detail="key_retired"``).
Not safe for concurrent use: the driver serializes.  Vectors: ``tests/vectors/epochs.json``.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import math
import struct
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum
from typing import NamedTuple, Protocol

from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.hmac import HMAC
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from antireplay.core.counters import FencedTable
from antireplay.core.errors import (
    ConfigError,
    EpochReplayedError,
    EpochTooFarAheadError,
    InvalidFrameError,
    MessageStaleError,
    ReplayAttackError,
    SignatureInvalidError,
    WarningCode,
)

VERSION = 1
PREFIX_LEN, TAG_LEN = 8, 32
HEAD = struct.Struct(">BB8sQ")
MIN_LEN = HEAD.size + TAG_LEN
MAX_LEN = 65_536
EPOCH_LIMIT = 2**64 - 1
RECENT_PER_PREFIX = 64
#: An authentic, unseen epoch this close below ``last`` is taken for a second sender.
COLLISION_HORIZON_NS = 60 * 1_000_000_000


class Kind(IntEnum):
    ANNOUNCEMENT = 1
    PING = 2
    #: A fresh verifier's question (payload: its nonce) and a signer's answer binding that
    #: nonce to its current (prefix, epoch); both sealed with the binding-ping key.
    CHALLENGE = 3
    ANSWER = 4


_TRAILERS = {kind: bytes((VERSION, kind)) for kind in Kind}  # a tag's last two bytes
LABELS = {Kind.ANNOUNCEMENT: "announcement", Kind.PING: "binding ping"}
#: The kinds that carry epochs a verifier keeps marks for.
STREAMS = (Kind.ANNOUNCEMENT, Kind.PING)
NONCE_LEN = 16
#: Challenge nonces a verifier keeps outstanding (the newest; a retry replaces the oldest).
OUTSTANDING = 4


@dataclass(frozen=True)
class Announcement:
    """An authentic, fresh announcement (or ping): only now may a lease be renewed."""

    payload: bytes
    nonce_prefix: bytes
    epoch: int
    kind: Kind = Kind.ANNOUNCEMENT
    #: Set when the sender is accepted but something must be reported.
    warning: WarningCode | None = None


class FleetKey(Protocol):
    """A fleet key kept in a PKCS#11 token as its HKDF-extracted PRK
    (``HMAC-SHA256(32 zero bytes, psk)``): ``.mac(data)`` is ``HMAC-SHA256(PRK, data)``
    computed there (:class:`antireplay.keys.pkcs11.TokenMac`)."""

    def mac(self, data: bytes, /) -> bytes: ...


def hkdf32(psk: bytes | FleetKey, info: bytes) -> bytes:
    """``HKDF-SHA256(psk, salt=None, info)``, 32 bytes; from a :class:`FleetKey` the token
    runs the expand step (``T(1) = HMAC(PRK, info | 0x01)``, RFC 5869), so both give the
    same key and a token-held fleet key interoperates with a file-held one."""
    if isinstance(psk, bytes):
        if len(psk) < 16:
            raise ValueError("psk must be at least 16 bytes")
        return HKDF(algorithm=hashes.SHA256(), length=32, salt=None, info=info).derive(psk)
    if not callable(getattr(psk, "mac", None)):
        raise ValueError("psk must be at least 16 bytes, or a fleet key in a token")
    return psk.mac(info + b"\x01")


def derive_key(psk: bytes | FleetKey, kind: Kind) -> bytes:
    """HKDF-SHA256 with a fixed label per kind; challenges and answers use the ping key
    (the kind byte under the MAC keeps the three apart)."""
    label = LABELS[kind if kind in STREAMS else Kind.PING]
    return hkdf32(psk, b"antireplay/v1 epoch " + label.encode())


def derive_keys(psk: bytes | FleetKey) -> dict[Kind, bytes]:
    """The key of every kind (two HKDF runs: challenges and answers share the ping key)."""
    keys = {k: derive_key(psk, k) for k in STREAMS}
    return keys | {Kind.CHALLENGE: keys[Kind.PING], Kind.ANSWER: keys[Kind.PING]}


#: The ``detail`` of a frame sealed with the retired fleet key after the cut-over.
KEY_RETIRED = "key_retired"


@dataclass(frozen=True)
class KeyRotation:
    """A rotation of the fleet key: its successor and the cut-over (wall-anchored ns)."""

    next_psk: bytes
    cutover_ns: int


class KeyRing:
    """The per-kind keys of the fleet key and, during a rotation, of its successor: which
    one seals an epoch, which ones verify a frame (module docstring)."""

    def __init__(self, psk: bytes, rotation: KeyRotation | None = None) -> None:
        self.current = derive_keys(psk)
        self.next = None if rotation is None else derive_keys(rotation.next_psk)
        self.cutover_ns = -1 if rotation is None else rotation.cutover_ns

    def sealing(self, epoch: int) -> dict[Kind, bytes]:
        """The keys an epoch is sealed with: the successor's from the cut-over on (a writer
        configured early keeps the old key until then, so a reader configured later but
        before the cut-over never meets a key it does not hold)."""
        return self.next if self.next is not None and epoch > self.cutover_ns else self.current

    def verify(self, claim: Claim) -> Refused | bool:
        """True when the tag verifies under a key in force for the frame's epoch; False
        when under none; a :class:`Refused` when only the retired key verifies an epoch
        after the cut-over (authentic, but that key may be in other hands by then)."""
        if _verifies(self.current[claim.kind], claim):
            if self.next is not None and claim.epoch > self.cutover_ns:
                retired = "sealed with the retired fleet key after its cut-over"
                return Refused(SignatureInvalidError(retired, detail=KEY_RETIRED))
            return True
        return self.next is not None and _verifies(self.next[claim.kind], claim)


def _verifies(key: bytes, claim: Claim) -> bool:
    expected = tag(key, claim.kind, claim.prefix, claim.epoch, claim.payload)
    return hmac.compare_digest(expected, claim.tag)


def prefix_for_service(service_name: str) -> bytes:
    """The nonce prefix of a named discovery service (names must be unique!)."""
    return hashlib.sha256(b"antireplay/v1 prefix" + service_name.encode()).digest()[:PREFIX_LEN]


def successor_prefix(prefix: bytes) -> bytes:
    """The prefix a signer rotates to after a forward clock glitch (public, deterministic)."""
    return hashlib.sha256(b"antireplay/v1 rotate" + prefix).digest()[:PREFIX_LEN]


@functools.lru_cache(maxsize=64)
def _keyed(key: bytes) -> HMAC:
    """HMAC-SHA256 keyed once per key: a tag copies it (no key schedule per frame)."""
    return HMAC(key, hashes.SHA256())


def tag(key: bytes, kind: Kind, prefix: bytes, epoch: int, payload: bytes) -> bytes:
    mac = _keyed(key).copy()
    mac.update(payload)
    mac.update(prefix + epoch.to_bytes(8, "big") + _TRAILERS[kind])
    return mac.finalize()


def require_size(payload: bytes) -> None:
    """A payload must leave the sealed frame within ``MAX_LEN``."""
    if len(payload) + MIN_LEN > MAX_LEN:
        raise ValueError("payload too large")


def seal(key: bytes, kind: Kind, prefix: bytes, epoch: int, payload: bytes) -> bytes:
    """The sealed frame for ``payload`` at ``(prefix, epoch)``."""
    require_size(payload)
    return (
        HEAD.pack(VERSION, kind, prefix, epoch) + payload + tag(key, kind, prefix, epoch, payload)
    )


def fence_reason(epoch: int, restart_ns: int, max_forward_ns: int) -> str:
    """What is known about an epoch at or below the restart fence (``restart_ns`` is the
    store's start plus ``max_forward_ns``): sealed before that start, a previous run may have
    accepted it; sealed after, only a sender's clock running ahead could have put it before a
    previous run, so the verifier waits for that sender's answer to its challenge."""
    if epoch <= restart_ns - max_forward_ns:
        return "sealed before this verifier's state began (a previous run may have accepted it)"
    return (
        "sealed within max_forward_s of this verifier's start, so not yet provably fresh: "
        "fenced, awaiting its writer's answer to this verifier's challenge"
    )


def to_ns(seconds: float) -> int:
    return int(seconds * 1_000_000_000)


def require_bound(name: str, seconds: float) -> None:
    """A bound in seconds must be positive and finite: an error names it, never a clamp."""
    if not 0 < seconds < math.inf:
        raise ConfigError(name, seconds, "a positive, finite number of seconds")


class Claim(NamedTuple):
    """A parsed sealed frame: what it claims, not yet judged (a tuple: built per frame)."""

    kind: Kind
    prefix: bytes
    epoch: int
    payload: bytes
    tag: bytes


def parse(sealed: bytes, kind: Kind) -> Claim:
    """The frame's fields, or ``INVALID_FRAME``."""
    if not isinstance(sealed, bytes):
        raise InvalidFrameError(f"{LABELS[kind]} must be bytes")
    if not MIN_LEN <= len(sealed) <= MAX_LEN:
        raise InvalidFrameError(f"{LABELS[kind]} must be {MIN_LEN}..{MAX_LEN} bytes")
    version, got_kind, prefix, epoch = HEAD.unpack_from(sealed)
    if version != VERSION:
        raise InvalidFrameError(f"unsupported version {version}")
    if got_kind != kind:
        raise InvalidFrameError(f"expected kind {int(kind)}, got {got_kind}")
    return Claim(kind, prefix, epoch, sealed[HEAD.size : -TAG_LEN], sealed[-TAG_LEN:])


def digest(payload: bytes) -> bytes:
    """What the collision judgement remembers of an accepted payload."""
    return hashlib.sha256(payload).digest()[:16]


@dataclass(frozen=True)
class TooFarAhead:
    """An authentic epoch beyond ``max_forward_s``: a sender's clock glitch, refused."""

    prefix: bytes
    epoch: int
    ahead_ns: int


@dataclass(frozen=True)
class PrefixCollision:
    """An authentic, unseen epoch just below the last: a second sender on the prefix?"""

    prefix: bytes
    epoch: int
    last: int


@dataclass(frozen=True)
class SenderRotated:
    """A new prefix that succeeds a known one: its sender left a stream that ran ahead."""

    previous: bytes
    prefix: bytes
    epoch: int


@dataclass(frozen=True)
class Refused:
    """A typed refusal and, for an authentic frame, the evidence the driver reports."""

    error: ReplayAttackError
    event: TooFarAhead | PrefixCollision | None = None


class Admission(NamedTuple):
    """An epoch the policy accepts, and what the driver must persist before the commit (a
    tuple: built per accepted frame, where a frozen dataclass costs a microsecond)."""

    #: The fence the commit raises (a prefix evicted), or None.
    floor: int | None
    #: The prefix is new to the table (its successor's marker is due).
    new: bool
    #: The prefix the commit evicts (its stored state is forgotten under ``floor``), or None.
    evicted: bytes | None = None


@dataclass
class Recent:
    """The last (epoch, digest) pairs of a live prefix, for the collision judgement."""

    pairs: deque[tuple[int, bytes]] = field(default_factory=lambda: deque(maxlen=RECENT_PER_PREFIX))


def rotation(
    claim: Claim, admission: Admission, unseen: bool, before: int | None
) -> SenderRotated | None:
    """A first accept anywhere of a prefix whose predecessor left its marker is a rotation."""
    if not (admission.new and unseen) or before is None:
        return None
    return SenderRotated(before.to_bytes(PREFIX_LEN, "big"), claim.prefix, claim.epoch)


class EpochPolicy:
    """Accepts each (prefix, epoch) at most once against its marks (module docstring)."""

    def __init__(
        self,
        psk: bytes,
        *,
        max_age_ns: int | None,
        max_forward_ns: int,
        max_prefixes: int,
        rotation: KeyRotation | None = None,
    ) -> None:
        self.ring = KeyRing(psk, rotation)
        self.keys = self.ring.current
        self.max_age_ns, self.max_forward_ns = max_age_ns, max_forward_ns
        self.tables: dict[Kind, FencedTable[bytes, Recent]] = {
            k: FencedTable(max_prefixes, what=f"{LABELS[k]} prefix") for k in STREAMS
        }
        self.max_answered = max_prefixes
        #: The nonces of this run's challenges, newest last (bounded).
        self.nonces: deque[bytes] = deque(maxlen=OUTSTANDING)
        #: Prefix -> the lowest epoch it answered one of those nonces with.
        self.answered: dict[bytes, int] = {}

    def authentic(self, claim: Claim) -> Refused | bool:
        """The tag verifies under a key in force (constant time; :meth:`KeyRing.verify`)."""
        return self.ring.verify(claim)

    def last(self, kind: Kind, prefix: bytes) -> int | None:
        """The mark the table holds for ``prefix`` (None: not held)."""
        return self.tables[kind].mark(prefix)

    def check_time(
        self, claim: Claim, now_ns: int, restart_ns: int, *, authentic: bool
    ) -> Refused | None:
        """Freshness against ``now_ns`` and the restart fence (the driver's store's)."""
        epoch = claim.epoch
        if self.max_age_ns is not None and epoch < now_ns - self.max_age_ns:
            return Refused(MessageStaleError(f"{LABELS[claim.kind]} older than max_age_s"))
        if epoch > now_ns + self.max_forward_ns:
            event = TooFarAhead(claim.prefix, epoch, epoch - now_ns) if authentic else None
            return Refused(EpochTooFarAheadError("epoch jumped beyond max_forward_s"), event)
        if epoch <= self.fence_for(claim.prefix, restart_ns):
            return Refused(MessageStaleError(fence_reason(epoch, restart_ns, self.max_forward_ns),
                                             detail="restart_fence"))  # fmt: skip
        return None

    def held(self, claim: Claim) -> Refused | bool:
        """Whether the table holds the prefix; an unknown one must be above the fence."""
        try:
            return self.tables[claim.kind].check(claim.prefix, claim.epoch) is not None
        except MessageStaleError as exc:
            return Refused(exc)

    def check_order(
        self, claim: Claim, digest: bytes, stored: int | None, *, authentic: bool
    ) -> Refused | bool:
        """``epoch > last[prefix]``; ``stored`` is the store's epoch for a prefix the table
        does not hold.  True when that store holds none (the prefix's first accept)."""
        table, epoch = self.tables[claim.kind], claim.epoch
        recent, last = table.get(claim.prefix), table.mark(claim.prefix)
        if recent is None or last is None:
            if stored is not None and epoch <= stored:
                return Refused(EpochReplayedError(f"epoch {epoch} is not above {stored}"))
            return stored is None
        if epoch > last:
            return False
        known = (epoch, digest) in recent.pairs
        if not authentic or known or not recent.pairs or last - epoch > COLLISION_HORIZON_NS:
            return Refused(EpochReplayedError(f"epoch {epoch} is not above {last}"))
        return Refused(
            EpochReplayedError("epoch not above last: nonce_prefix collision suspected"),
            PrefixCollision(claim.prefix, epoch, last),
        )

    def admit(self, claim: Claim) -> Refused | Admission:
        """What committing the epoch needs persisted first; a full table's newcomer must
        be above the lowest mark (scanned here: authenticated frames only)."""
        table = self.tables[claim.kind]
        try:
            evicted = table.admit(claim.prefix, claim.epoch)
        except MessageStaleError as exc:
            return Refused(exc)
        floor = None if evicted is None else max(table.fence, table.mark(evicted) or -1)
        return Admission(floor, claim.prefix not in table, evicted)

    def commit(self, claim: Claim, digest: bytes) -> None:
        """Move the marks; the driver has persisted what :meth:`admit` asked for."""
        recent = self.tables[claim.kind].commit(claim.prefix, claim.epoch, Recent)
        recent.pairs.append((claim.epoch, digest))

    def fence_for(self, prefix: bytes, restart_ns: int) -> int:
        """The restart fence, or lower for a prefix that answered a challenge: its epochs
        above the answered one were sealed after its signer saw a nonce of this run."""
        answered = self.answered.get(prefix)
        return restart_ns if answered is None else min(restart_ns, answered)

    def challenge(self, nonce: bytes, prefix: bytes, now_ns: int) -> bytes:
        """A sealed challenge for ``nonce`` (random, from the driver); the oldest nonce
        outstanding is dropped once ``OUTSTANDING`` are held."""
        if len(nonce) != NONCE_LEN:
            raise ValueError(f"a challenge nonce is {NONCE_LEN} bytes")
        self.nonces.append(nonce)
        key = self.ring.sealing(now_ns)[Kind.CHALLENGE]
        return seal(key, Kind.CHALLENGE, prefix, now_ns, nonce)

    def check_answer(self, claim: Claim) -> Refused | None:
        """Cheap, before the MAC: an answer must bind a nonce this run holds outstanding
        (a replayed answer binds a stale one)."""
        if claim.payload in self.nonces:
            return None
        stale = "answer to a challenge this verifier is not waiting for"
        return Refused(MessageStaleError(stale, detail="challenge_nonce"))

    def commit_answer(self, claim: Claim) -> None:
        """Record an authentic answer (checked first); a full map drops its oldest prefix,
        which falls back to the restart fence (closed, never open)."""
        previous = self.answered.get(claim.prefix)
        if previous is None and len(self.answered) >= self.max_answered:
            del self.answered[next(iter(self.answered))]
        lowest = claim.epoch if previous is None else min(previous, claim.epoch)
        self.answered[claim.prefix] = lowest

    def forget_answers(self) -> None:
        """The store lost state after the challenges: they prove nothing about it."""
        self.nonces.clear()
        self.answered.clear()
