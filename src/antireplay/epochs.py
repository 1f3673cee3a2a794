"""Epoch-authenticated announcements and binding pings (DDS discovery style), failure modes closed.

Theory of operation
-------------------
A sender (a DDS participant or discovery service) seals each announcement as ::

    sealed = version u8 | kind u8 | nonce_prefix[8] | epoch u64 (big-endian) | payload | tag[32]
    tag    = HMAC-SHA256(k_kind, payload | nonce_prefix | epoch u64 | version u8 | kind u8)
    k_kind = HKDF-SHA256(ikm=psk, salt="", info="antireplay/v1 epoch " + kind name)

``kind`` is 1 for announcements and 2 for binding pings; each kind has its own
key, so a ping can never be taken for an announcement.  ``nonce_prefix`` is 8
random bytes per sender, or ``SHA-256("antireplay/v1 prefix" | service_name)[:8]``
for a named discovery service (two instances must never share a name; the
verifier reports it when they do).  Test vectors: ``tests/vectors/epochs.json``.

**Epochs are wall-anchored nanoseconds.**  ``epoch = max(last + 1, wall_ns)``:
strictly increasing, and never below the current time.  The signer takes them
from the one sender source, a wall-anchored
:class:`~antireplay.core.counters.NonceCounter`.  Consequences:

* a verifier that has never heard of a sender can still refuse an
  announcement older than ``max_age_s`` (a capture from yesterday);
* a wall-clock step backwards never makes epochs regress (``last + 1`` wins
  until the clock catches up); a step forwards makes them jump, which
  verifiers bound with ``max_forward_s``.

**Forward glitches rotate the stream.**  If the clock jumps ahead for one seal
and NTP then corrects it, ``last + 1`` stays far ahead and every verifier with
``max_forward_s`` would refuse the sender until real time caught up (a
one-second glitch, an hour's lockout).  So before each seal the signer compares
its last epoch with the wall clock: when ``last`` is more than the signer's
``max_forward_s`` ahead (set it at or below the verifiers' bound, and above
``reserve_s``), it **rotates**: it moves to the successor prefix
``SHA-256("antireplay/v1 rotate" | prefix)[:8]`` and starts that new stream at
the current time.  No epoch is ever repeated or lowered *within a prefix* (the
old prefix is simply never used again; a successor chain cannot cycle short of
a hash collision), so the strict-increase invariant holds.  The lockout lasts
only until the first seal after the clock is corrected.  The signer cannot tell
a corrected forward glitch from a backward step of a clock that was right, so a
backward step larger than the bound also rotates; the new stream then carries
the current (possibly wrong) time and verifiers judge it against their own
clocks with ``max_age_s``, exactly as they judge any sender whose clock is off.

Verifiers alarm: an unknown prefix that is the successor of a known one is
accepted as a new stream (it is above nothing; the fences and ``max_age_s``
still apply) and answered with ``warning="EPOCH_SENDER_ROTATED"``, counted in
``rotations``/``warnings``, logged, and audited when the verifier has an
audit log; the glitched epoch itself was refused with ``EPOCH_TOO_FAR_AHEAD``
(counted in ``forward_rejections``, also audited).  A rotation is reported
once, when the store holds no epoch for the new prefix yet: a verifier
restarted on the same store, or one that evicted the prefix and admits it
again, does not report it again (two verifiers racing on a shared store for
the new prefix's first epochs may both report it).

**State file and rotation.**  The signer's state file records the current
prefix, the prefix it started from (``base``: what ``nonce_prefix`` or
``service_name`` must match at the next start) and the rotation count.  A
rotation saves the new prefix and its first ceiling *before* the first epoch
under it is emitted, so a crash never re-uses a prefix at a lower epoch.  A
glitched ceiling that reached the file (the glitch was persisted, then the
host restarted) is recovered the same way: the restored ``last`` is more than
the bound ahead of the clock, so the first seal after the restart rotates.

**Crash safety.**  With ``state_file`` the signer persists a reserved ceiling
through :mod:`antireplay.state.durable` before emitting any epoch above the previous
one, reserving ``reserve_s`` (default 1 s) of epochs at a time, so a busy
sender fsyncs about once a second, not per message.  After a crash or a host
reboot it starts above the ceiling, above anything it could have sent.  Choose
``max_forward_s`` at verifiers larger than ``reserve_s``.  The state file has
one owner (an OS lock, :mod:`antireplay.state.durable`): two signers on one file
would emit the same epochs.  Running out of epochs (``2**64`` ns, the year
2554) is the signer's own :class:`~antireplay.core.errors.NonceExhaustedError`.

**The verifier keeps its state in a replay store** (:mod:`antireplay.state`:
``memory``, ``sqlite:PATH``, Redis), the contract every receiver shares.  Each
accepted epoch is **one** ``advance`` of the key ``NAMESPACE:KIND:PREFIX``
(compare-and-advance, atomic on every backend, durable before ``open``
returns with SQLite or Redis), so a restarted verifier, or another one on the
same store, refuses everything accepted or superseded.  A prefix's first
accept also advances ``NAMESPACE:KIND:after:SUCCESSOR`` to the prefix, which
is how a rotated sender is recognised, even by a restarted verifier.

**Two phases.**  :meth:`EpochVerifier.check` records and counts nothing: shape,
freshness, fences and order, the MAC aside.  :meth:`EpochVerifier.open` is the
recipe: parse, constant-time tag check, the same checks, then the commit under
a lock.  The tag comes first in ``open`` (HMAC is cheap) because what an
*authentic* far-ahead or old epoch means (a clock glitch, a second sender on a
prefix) is counted and audited; a bad tag changes no state.  An authentic
epoch too far ahead is refused and counted (``forward_rejections``) instead
of locking the sender out.  Callers renew a participant's lease only with the
returned :class:`Announcement`: a replayed old announcement raises and renews
nothing.

**Fences.**  The in-memory prefix table (recent digests, the last epoch) is a
bounded :class:`~antireplay.core.counters.FencedTable`: evicting the prefix with
the oldest epoch raises its fence (persisted as ``NAMESPACE:KIND:floor``), and
an unknown prefix at or below it is refused with ``MESSAGE_STALE``
(``detail="fence"``).  The store's own fence (a memory store's start, a lost
SQLite file, a restarted Redis) plus ``max_forward_s``, the furthest ahead any
sender may run, is the **restart fence**: epochs at or below it may have been
accepted by state that is gone, and are refused (``detail="restart_fence"``).
So a verifier without persistent state refuses everything sealed before it
started.  ``max_forward_s`` is always in force (a positive, finite number of
seconds; default 60 s, the signer's default, while DDS readers default to 5 s);
``max_age_s`` defaults to None here (no age bound: a never-seen sender is
judged by the fences alone), and DDS readers always set it (default 30 s).

**Prefix collisions.**  An *authentic* announcement with an epoch at or below
``last[prefix]`` (but within 60 s of it) that is not one the verifier accepted
(it remembers the last 64 (epoch, digest) pairs per prefix) most likely comes
from a second sender using the same prefix: it is rejected, logged, and
counted in ``prefix_collisions``.  Network reordering or a replay of a frame
the verifier never received can cause an occasional false report; two senders
sharing a prefix produce a steady stream, so alert on the rate.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import math
import os
import struct
import threading
from collections import Counter, deque
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from antireplay.core.clock import Clock, resolve
from antireplay.core.counters import FencedTable, NonceCounter
from antireplay.core.errors import (
    Code,
    ConfigError,
    EpochReplayedError,
    EpochTooFarAheadError,
    InvalidFrameError,
    MessageStaleError,
    SignatureInvalidError,
    StateFileError,
    WarningCode,
)
from antireplay.state import ReplayStore, open_store
from antireplay.state.ceilings import counter_on_state
from antireplay.state.durable import DurableState, as_hex, as_int, register_repair
from antireplay.state.memory import MemoryStore

if TYPE_CHECKING:
    from antireplay.audit import AuditLog

log = logging.getLogger("antireplay.epochs")

VERSION = 1
PREFIX_LEN, TAG_LEN = 8, 32
_HEAD = struct.Struct(">BB8sQ")
MIN_LEN = _HEAD.size + TAG_LEN
MAX_LEN = 65_536
EPOCH_LIMIT = 2**64 - 1
RECENT_PER_PREFIX = 64
#: An authentic, unseen epoch this close below ``last`` is taken for a second sender.
COLLISION_HORIZON_NS = 60 * 1_000_000_000


class Kind(IntEnum):
    ANNOUNCEMENT = 1
    PING = 2


_LABELS = {Kind.ANNOUNCEMENT: "announcement", Kind.PING: "binding ping"}


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
    info = b"antireplay/v1 epoch " + _LABELS[kind].encode()
    return HKDF(algorithm=hashes.SHA256(), length=32, salt=None, info=info).derive(psk)


def prefix_for_service(service_name: str) -> bytes:
    """The nonce prefix of a named discovery service (names must be unique!)."""
    return hashlib.sha256(b"antireplay/v1 prefix" + service_name.encode()).digest()[:PREFIX_LEN]


def successor_prefix(prefix: bytes) -> bytes:
    """The prefix a signer rotates to after a forward clock glitch (public, deterministic)."""
    return hashlib.sha256(b"antireplay/v1 rotate" + prefix).digest()[:PREFIX_LEN]


def _tag(key: bytes, kind: Kind, prefix: bytes, epoch: int, payload: bytes) -> bytes:
    trailer = prefix + epoch.to_bytes(8, "big") + bytes([VERSION, kind])
    return hmac.digest(key, payload + trailer, "sha256")


def _wall_ns(clock: Clock) -> int:
    return int(clock.wall() * 1_000_000_000)


@dataclass(frozen=True)
class _SignerState:
    prefix: bytes
    base: bytes
    ceiling: int
    rotations: int


def _parse_signer(data: dict[str, Any]) -> _SignerState:
    prefix = as_hex(data["prefix"], "prefix", PREFIX_LEN)
    base = as_hex(data.get("base", data["prefix"]), "base", PREFIX_LEN)
    return _SignerState(
        prefix,
        base,
        as_int(data["ceiling"], "ceiling"),
        as_int(data.get("rotations", 0), "rotations"),
    )


class EpochSigner:
    """Seals announcements with strictly increasing, wall-anchored, crash-safe epochs."""

    def __init__(
        self,
        psk: bytes,
        *,
        nonce_prefix: bytes | None = None,
        service_name: str | None = None,
        state_file: str | os.PathLike[str] | None = None,
        clock: Clock | None = None,
        reserve_s: float = 1.0,
        max_forward_s: float = 60.0,
    ) -> None:
        if nonce_prefix is not None and service_name is not None:
            raise ValueError("give nonce_prefix or service_name, not both")
        if service_name is not None:
            nonce_prefix = prefix_for_service(service_name)
        if nonce_prefix is not None and len(nonce_prefix) != PREFIX_LEN:
            raise ValueError(f"nonce_prefix must be {PREFIX_LEN} bytes")
        if not max_forward_s > reserve_s:
            raise ValueError("max_forward_s must exceed reserve_s (else every restart rotates)")
        self._keys = {k: derive_key(psk, k) for k in Kind}
        self._clock = clock = resolve(clock)
        self._max_forward_ns = int(max_forward_s * 1_000_000_000)
        self._lock = threading.Lock()
        self.rotations = 0
        self.nonce_prefix = nonce_prefix if nonce_prefix is not None else os.urandom(PREFIX_LEN)
        self.base_prefix = self.nonce_prefix

        def anchor() -> int:
            return _wall_ns(clock)

        if state_file is None:
            self._epochs = NonceCounter(1, limit=EPOCH_LIMIT, anchor=anchor)
            return
        state = DurableState(Path(state_file), kind="epoch-signer", exclusive=True)
        wanted, path = nonce_prefix, str(state_file)

        def parse(data: dict[str, Any]) -> _SignerState:
            got = _parse_signer(data)
            if wanted is not None and got.base != wanted:
                raise StateFileError(path, "holds state for another nonce_prefix")
            return got

        stored: _SignerState | None = state.load(parse)
        if stored is not None:
            self.rotations = stored.rotations
            self.nonce_prefix, self.base_prefix = stored.prefix, stored.base
        self._epochs = counter_on_state(
            state, 0 if stored is None else stored.ceiling, int(reserve_s * 1_000_000_000) + 1,
            limit=EPOCH_LIMIT, anchor=anchor, record=self._record,
        )  # fmt: skip

    def _record(self, ceiling: int) -> dict[str, Any]:
        """What the state file holds: the ceiling and the prefix it belongs to."""
        return {"ceiling": ceiling, "prefix": self.nonce_prefix.hex(),
                "base": self.base_prefix.hex(), "rotations": self.rotations}  # fmt: skip

    @property
    def last_epoch(self) -> int:
        return self._epochs.last

    def close(self) -> None:
        """Give up the state file (its lock)."""
        self._epochs.close()

    def next_epoch(self) -> int:
        """Reserve and return the next epoch (persisting a new ceiling first if needed)."""
        return self._next()[1]

    def _next(self) -> tuple[bytes, int]:
        """The (prefix, epoch) pair to seal with, taken together under the lock."""
        with self._lock:
            ahead = self._epochs.last - _wall_ns(self._clock)
            if ahead > self._max_forward_ns:
                self._rotate(ahead)
            return self.nonce_prefix, self._epochs.next()

    def _rotate(self, ahead: int) -> None:
        """Leave a stream whose last epoch ran ahead of the clock (module docstring)."""
        log.warning(
            "epoch stream %s is %.1fs ahead of the clock (a forward glitch, now corrected?); "
            "rotating to a new prefix",
            self.nonce_prefix.hex(),
            ahead / 1e9,
        )
        self.nonce_prefix = successor_prefix(self.nonce_prefix)
        self.rotations += 1
        self._epochs.restart()  # a new binding; persisted (new prefix) before its first epoch

    def seal(self, payload: bytes, *, kind: Kind = Kind.ANNOUNCEMENT) -> bytes:
        """Seal one announcement (or, with ``kind=Kind.PING``, one binding ping)."""
        if len(payload) + MIN_LEN > MAX_LEN:
            raise ValueError("payload too large")
        prefix, epoch = self._next()
        head = _HEAD.pack(VERSION, kind, prefix, epoch)
        return head + payload + _tag(self._keys[kind], kind, prefix, epoch, payload)

    def seal_ping(self, payload: bytes) -> bytes:
        """A binding ping: same discipline, separate key."""
        return self.seal(payload, kind=Kind.PING)


@dataclass
class _Recent:
    """What the verifier remembers of a live prefix beyond its mark: its store key, and the
    last (epoch, digest) pairs for the collision judgement."""

    key: str
    pairs: deque[tuple[int, bytes]] = field(default_factory=lambda: deque(maxlen=RECENT_PER_PREFIX))


class _Claim(NamedTuple):
    """A parsed sealed frame: what it claims, not yet judged (a tuple: built per frame)."""

    kind: Kind
    prefix: bytes
    epoch: int
    payload: bytes
    tag: bytes


class EpochVerifier:
    """Accepts each (prefix, epoch) at most once, on a replay store (module docstring)."""

    def __init__(
        self,
        psk: bytes,
        *,
        store: ReplayStore | str | None = None,
        namespace: str = "epoch",
        max_age_s: float | None = None,
        max_forward_s: float = 60.0,
        clock: Clock | None = None,
        max_prefixes: int = 4096,
        audit: AuditLog | None = None,
    ) -> None:
        if max_age_s is not None:
            _require_bound("max_age_s", max_age_s)
        _require_bound("max_forward_s", max_forward_s)
        self._keys = {k: derive_key(psk, k) for k in Kind}
        self._clock = resolve(clock)
        self.max_age_ns = None if max_age_s is None else int(max_age_s * 1e9)
        self.max_forward_s = max_forward_s
        self.max_forward_ns = int(max_forward_s * 1e9)
        self.audit = audit
        self.namespace = namespace
        self._owns_store = not isinstance(store, ReplayStore)
        if store is None:
            store = MemoryStore(max_entries=1, clock=self._clock)
        elif isinstance(store, str):
            store = open_store(store, clock=self._clock)
        self.store: ReplayStore = store
        self._lock = threading.Lock()
        self._tables: dict[Kind, FencedTable[bytes, _Recent]] = {
            k: FencedTable(max_prefixes, what=f"{_LABELS[k]} prefix") for k in Kind
        }
        self.prefix_collisions = 0
        self.forward_rejections = 0
        self.rotations = 0
        self.warnings: Counter[WarningCode] = Counter()
        self._fence_seen, self._restart_ns = -math.inf, -1
        self.store.verify()  # loss detection now: a lost store raises its fence
        for kind, table in self._tables.items():
            table.raise_fence(self.store.current(self._key(kind, "floor")) or -1)

    @property
    def max_prefixes(self) -> int:
        return self._tables[Kind.ANNOUNCEMENT].max_keys

    def close(self) -> None:
        """Close the store if this verifier opened it."""
        if self._owns_store:
            self.store.close()

    def _key(self, kind: Kind, name: str) -> str:
        return f"{self.namespace}:{kind.name.lower()}:{name}"

    def restart_fence(self) -> int:
        """Epochs at or below this may have been accepted by a run whose state the store
        lost (or by a previous process, for the memory store): the store's fence plus
        ``max_forward_s``, the furthest ahead any sender could have been.  -1: none."""
        fence = self.store.fence()
        if fence != self._fence_seen:  # rare: computed once per fence the store reports
            self._fence_seen = fence
            self._restart_ns = int((fence + self.max_forward_s) * 1e9)
        return self._restart_ns

    def last(self, prefix: bytes, kind: Kind = Kind.ANNOUNCEMENT) -> int | None:
        """The last epoch committed from ``prefix`` (None if unknown)."""
        mark = self._tables[kind].mark(prefix)
        return mark if mark is not None else self.store.current(self._key(kind, prefix.hex()))

    def open_ping(self, sealed: bytes) -> Announcement:
        return self.open(sealed, kind=Kind.PING)

    def check(self, sealed: bytes, *, kind: Kind = Kind.ANNOUNCEMENT) -> None:
        """Raise the typed reason ``sealed`` would be refused, the MAC aside; records
        nothing and counts nothing (an unauthenticated frame carries no evidence)."""
        claim = _parse(sealed, kind)
        self._check_time(claim, authentic=False)
        with self._lock:
            self._check_order(claim, b"", authentic=False)

    def open(self, sealed: bytes, *, kind: Kind = Kind.ANNOUNCEMENT) -> Announcement:
        """The recipe: parse, authenticate (HMAC, cheap), check, commit; raises a typed
        error otherwise.  The MAC runs before the order check because what an *authentic*
        old or far-ahead epoch means (a collision, a glitch) is counted and audited."""
        claim = _parse(sealed, kind)
        expected = _tag(self._keys[kind], kind, claim.prefix, claim.epoch, claim.payload)
        if not hmac.compare_digest(expected, claim.tag):
            raise SignatureInvalidError("announcement tag does not verify")
        self._check_time(claim, authentic=True)
        digest = hashlib.sha256(claim.payload).digest()[:16]
        with self._lock:
            unseen = self._check_order(claim, digest, authentic=True)
            rotated_from = self._commit(claim, digest, unseen)
        accepted = Announcement(claim.payload, claim.prefix, claim.epoch, kind)
        return accepted if rotated_from is None else self._rotated(accepted, rotated_from)

    def _commit(self, claim: _Claim, digest: bytes, unseen: bool) -> bytes | None:
        """Record the epoch (caller holds the lock and has checked it): one store
        ``advance``; a prefix new to the table leaves its successor's marker, and one
        ``unseen`` by the store too learns whether it succeeds a known one."""
        kind, prefix, epoch = claim.kind, claim.prefix, claim.epoch
        table = self._tables[kind]
        fence, new = table.fence, prefix not in table
        entry = table.commit(prefix, epoch, lambda: _Recent(self._key(kind, prefix.hex())))
        if table.fence != fence:
            self.store.advance(self._key(kind, "floor"), table.fence)
        if not self.store.advance(entry.key, epoch):
            raise EpochReplayedError(f"epoch {epoch} already committed to the shared state")
        if epoch <= self.restart_fence():  # the advance itself noticed lost state
            raise MessageStaleError("the verifier's store lost state", detail="restart_fence")
        entry.pairs.append((epoch, digest))
        if not new:
            return None
        self.store.advance(
            self._key(kind, "after:" + successor_prefix(prefix).hex()), int.from_bytes(prefix)
        )
        if not unseen:  # the store knew this prefix: any rotation to it was reported then
            return None
        before = self.store.current(self._key(kind, "after:" + prefix.hex()))
        if before is None:
            return None
        self.rotations += 1
        self.warnings[WarningCode.EPOCH_SENDER_ROTATED] += 1
        return before.to_bytes(PREFIX_LEN)

    def _rotated(self, accepted: Announcement, previous: bytes) -> Announcement:
        """A sender left a stream that ran ahead of its clock: accept, count, log, audit."""
        code = WarningCode.EPOCH_SENDER_ROTATED  # counted under the lock in _commit()
        log.warning(
            "sender rotated from nonce_prefix %s to %s (its clock ran ahead, then was corrected)",
            previous.hex(),
            accepted.nonce_prefix.hex(),
        )
        self._audit("accepted", None, code, accepted.nonce_prefix, accepted.epoch)
        return Announcement(accepted.payload, accepted.nonce_prefix, accepted.epoch,
                            accepted.kind, code)  # fmt: skip

    def _audit(
        self, outcome: str, code: str | None, warning: str | None, prefix: bytes, epoch: int
    ) -> None:
        if self.audit is not None:
            self.audit.append(
                at=self._clock.wall(), outcome=outcome, code=code, warning=warning,
                msg_type=None, sender=f"epoch:{prefix.hex()}", sender_verified=True,
                msg_id=str(epoch),
            )  # fmt: skip

    def _check_time(self, claim: _Claim, *, authentic: bool) -> None:
        """Freshness against this verifier's clock and its store's restart fence."""
        epoch, now = claim.epoch, _wall_ns(self._clock)
        if self.max_age_ns is not None and epoch < now - self.max_age_ns:
            raise MessageStaleError("announcement older than max_age_s")
        if epoch > now + self.max_forward_ns:
            if authentic:
                self.forward_rejections += 1
                log.warning("authentic epoch %d is %.1fs ahead", epoch, (epoch - now) / 1e9)
                self._audit("rejected", Code.EPOCH_TOO_FAR_AHEAD, None, claim.prefix, epoch)
            raise EpochTooFarAheadError("epoch jumped beyond max_forward_s")
        if epoch <= self.restart_fence():
            raise MessageStaleError(
                "sealed before this verifier's state began (a previous run may have accepted it)",
                detail="restart_fence",
            )

    def _check_order(self, claim: _Claim, digest: bytes, *, authentic: bool) -> bool:
        """``epoch > last[prefix]`` (caller holds the lock); records nothing.  True when
        the store holds no epoch for the prefix (its first accept anywhere)."""
        table, epoch = self._tables[claim.kind], claim.epoch
        recent = table.check(claim.prefix, epoch)
        if recent is None:
            stored = self.store.current(self._key(claim.kind, claim.prefix.hex()))
            if stored is not None and epoch <= stored:
                raise EpochReplayedError(f"epoch {epoch} is not above {stored}")
            return stored is None
        last = table.mark(claim.prefix)
        assert last is not None
        if epoch > last:
            return False
        if authentic:
            self._judge_old(claim.prefix, epoch, digest, last, recent)
        raise EpochReplayedError(f"epoch {epoch} is not above {last}")

    def _judge_old(
        self, prefix: bytes, epoch: int, digest: bytes, last: int, recent: _Recent
    ) -> None:
        """An authentic old epoch: a replay of ours, or a second sender on the same prefix."""
        known = (epoch, digest) in recent.pairs
        if known or not recent.pairs or last - epoch > COLLISION_HORIZON_NS:
            raise EpochReplayedError(f"epoch {epoch} is not above {last}")
        self.prefix_collisions += 1
        log.warning(
            "nonce_prefix %s used by two senders (authentic epoch %d <= %d never accepted)",
            prefix.hex(),
            epoch,
            last,
        )
        raise EpochReplayedError("epoch not above last: nonce_prefix collision suspected")


def _require_bound(name: str, seconds: float) -> None:
    """A bound in seconds must be positive and finite: an error names it, never a clamp."""
    if not 0 < seconds < math.inf:
        raise ConfigError(name, seconds, "a positive, finite number of seconds")


def _parse(sealed: bytes, kind: Kind) -> _Claim:
    if not isinstance(sealed, bytes):
        raise InvalidFrameError("announcement must be bytes")
    if not MIN_LEN <= len(sealed) <= MAX_LEN:
        raise InvalidFrameError(f"announcement must be {MIN_LEN}..{MAX_LEN} bytes")
    version, got_kind, prefix, epoch = _HEAD.unpack_from(sealed)
    if version != VERSION:
        raise InvalidFrameError(f"unsupported version {version}")
    if got_kind != kind:
        raise InvalidFrameError(f"expected kind {int(kind)}, got {got_kind}")
    return _Claim(kind, prefix, epoch, sealed[_HEAD.size : -TAG_LEN], sealed[-TAG_LEN:])


def _int_or(value: object, default: int) -> int:
    return value if isinstance(value, int) and not isinstance(value, bool) else default


def _reseed_signer(data: dict[str, Any] | None, now_ns: int) -> dict[str, Any]:
    """Above the salvaged ceiling and above the current time; keep the prefix if readable."""
    data = data or {}
    try:
        prefix = as_hex(data.get("prefix"), "prefix", PREFIX_LEN).hex()
    except TypeError:
        prefix = os.urandom(PREFIX_LEN).hex()
    try:
        base = as_hex(data.get("base", prefix), "base", PREFIX_LEN).hex()
    except TypeError:
        base = prefix
    return {
        "ceiling": max(_int_or(data.get("ceiling"), 0), now_ns), "prefix": prefix,
        "base": base, "rotations": _int_or(data.get("rotations"), 0),
    }  # fmt: skip


register_repair("epoch-signer", _reseed_signer)
