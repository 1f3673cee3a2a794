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
per kind, with the last (epoch, digest) pairs of each prefix) and judges values with a
time the driver passes in.  A refusal comes back as :class:`Refused` (the typed error and,
for an authentic frame, the evidence: :class:`TooFarAhead`, :class:`PrefixCollision`); an
acceptable epoch as an :class:`Admission` saying what must be persisted (a raised floor, a
new prefix).  The driver persists, then calls :meth:`EpochPolicy.commit`; nothing here
moves a mark before that.  An authentic epoch at or below the last one, unseen and within
``COLLISION_HORIZON_NS``, most likely comes from a second sender on the prefix.  Not safe
for concurrent use: the driver serializes.  Test vectors: ``tests/vectors/epochs.json``.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import struct
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum
from typing import NamedTuple

from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from antireplay.core.counters import FencedTable
from antireplay.core.errors import (
    ConfigError,
    EpochReplayedError,
    EpochTooFarAheadError,
    InvalidFrameError,
    MessageStaleError,
    ReplayAttackError,
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


LABELS = {Kind.ANNOUNCEMENT: "announcement", Kind.PING: "binding ping"}


@dataclass(frozen=True)
class Announcement:
    """An authentic, fresh announcement (or ping): only now may a lease be renewed."""

    payload: bytes
    nonce_prefix: bytes
    epoch: int
    kind: Kind = Kind.ANNOUNCEMENT
    #: Set when the sender is accepted but something must be reported.
    warning: WarningCode | None = None


def derive_key(psk: bytes, kind: Kind) -> bytes:
    """HKDF-SHA256 with a fixed label per kind."""
    if not isinstance(psk, bytes) or len(psk) < 16:
        raise ValueError("psk must be at least 16 bytes")
    info = b"antireplay/v1 epoch " + LABELS[kind].encode()
    return HKDF(algorithm=hashes.SHA256(), length=32, salt=None, info=info).derive(psk)


def prefix_for_service(service_name: str) -> bytes:
    """The nonce prefix of a named discovery service (names must be unique!)."""
    return hashlib.sha256(b"antireplay/v1 prefix" + service_name.encode()).digest()[:PREFIX_LEN]


def successor_prefix(prefix: bytes) -> bytes:
    """The prefix a signer rotates to after a forward clock glitch (public, deterministic)."""
    return hashlib.sha256(b"antireplay/v1 rotate" + prefix).digest()[:PREFIX_LEN]


def tag(key: bytes, kind: Kind, prefix: bytes, epoch: int, payload: bytes) -> bytes:
    trailer = prefix + epoch.to_bytes(8, "big") + bytes([VERSION, kind])
    return hmac.digest(key, payload + trailer, "sha256")


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


@dataclass(frozen=True)
class Admission:
    """An epoch the policy accepts, and what the driver must persist before the commit."""

    #: The fence the commit raises (a prefix evicted), or None.
    floor: int | None
    #: The prefix is new to the table (its successor's marker is due).
    new: bool


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
        self, psk: bytes, *, max_age_ns: int | None, max_forward_ns: int, max_prefixes: int
    ) -> None:
        self.keys = {k: derive_key(psk, k) for k in Kind}
        self.max_age_ns, self.max_forward_ns = max_age_ns, max_forward_ns
        self.tables: dict[Kind, FencedTable[bytes, Recent]] = {
            k: FencedTable(max_prefixes, what=f"{LABELS[k]} prefix") for k in Kind
        }

    def authentic(self, claim: Claim) -> bool:
        """The tag verifies (constant time)."""
        expected = tag(self.keys[claim.kind], claim.kind, claim.prefix, claim.epoch, claim.payload)
        return hmac.compare_digest(expected, claim.tag)

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
        if epoch <= restart_ns:
            return Refused(
                MessageStaleError(
                    "sealed before this verifier's state began "
                    "(a previous run may have accepted it)",
                    detail="restart_fence",
                )
            )
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
        return Admission(floor, claim.prefix not in table)

    def commit(self, claim: Claim, digest: bytes) -> None:
        """Move the marks; the driver has persisted what :meth:`admit` asked for."""
        recent = self.tables[claim.kind].commit(claim.prefix, claim.epoch, Recent)
        recent.pairs.append((claim.epoch, digest))
