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
strictly increasing, and never below the current time.  Consequences:

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
accepted as a new stream (it is above nothing; the floor and ``max_age_s``
still apply) and answered with ``warning="EPOCH_SENDER_ROTATED"``, counted in
``rotations``/``warnings``, logged, and audited when the verifier has an
audit log; the glitched epoch itself was refused with ``EPOCH_TOO_FAR_AHEAD``
(counted in ``forward_rejections``, also audited).

**State file and rotation.**  The signer's state file records the current
prefix, the prefix it started from (``base``: what ``nonce_prefix`` or
``service_name`` must match at the next start) and the rotation count.  A
rotation saves the new prefix and its first ceiling *before* the first epoch
under it is emitted, so a crash never re-uses a prefix at a lower epoch.  A
glitched ceiling that reached the file (the glitch was persisted, then the
host restarted) is recovered the same way: the restored ``last`` is more than
the bound ahead of the clock, so the first seal after the restart rotates.

**Crash safety.**  With ``state_file`` the signer persists a reserved ceiling
through :mod:`antireplay.durable` before emitting any epoch above the previous
one, reserving ``reserve_s`` (default 1 s) of epochs at a time, so a busy
sender fsyncs about once a second, not per message.  After a crash or a host
reboot it starts above the ceiling, above anything it could have sent.  Choose
``max_forward_s`` at verifiers larger than ``reserve_s``.

**One owner per state file.**  Signer and verifier state files are opened
with an OS lock (:mod:`antireplay.durable`): a second process on the same file
is refused, since two signers on one file would emit the same epochs.

**Verifier order.**  Parse, constant-time tag check (HMAC is cheap), freshness
(``max_age_s``, ``max_forward_s``), then ``epoch > last[prefix]``, then the
commit under a lock.  A bad tag changes no state; an authentic epoch too far
ahead is refused and counted (``forward_rejections``) instead of locking the
sender out.  Callers renew a participant's lease only with the returned
:class:`Announcement`: a replayed old announcement raises and renews nothing.
With ``state_file`` every accepted epoch is persisted before ``open`` returns,
so a restarted verifier rejects everything it had accepted or superseded.
The prefix table is bounded: evicting the prefix with the oldest epoch raises a
``floor``, and unknown prefixes must be above it.

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
import os
import struct
import threading
from collections import Counter, deque
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from antireplay.clock import Clock, resolve
from antireplay.durable import DurableState, as_hex, as_int, register_repair
from antireplay.errors import (
    AuthenticationError,
    Code,
    EpochReplayError,
    EpochTooFarAheadError,
    InvalidFrameError,
    MessageStaleError,
    StateFileError,
    WarningCode,
)

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
    #: Set when the sender is accepted but something must be reported (see WarningCode).
    warning: str | None = None


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
        self._clock = resolve(clock)
        self._reserve_ns = int(reserve_s * 1_000_000_000)
        self._max_forward_ns = int(max_forward_s * 1_000_000_000)
        self._lock = threading.Lock()
        self._last = 0
        self._ceiling = EPOCH_LIMIT
        self.rotations = 0
        self._state: DurableState | None = None
        stored: _SignerState | None = None
        if state_file is not None:
            self._state = DurableState(Path(state_file), kind="epoch-signer", exclusive=True)
            wanted, path = nonce_prefix, str(state_file)

            def parse(data: dict[str, Any]) -> _SignerState:
                got = _parse_signer(data)
                if wanted is not None and got.base != wanted:
                    raise StateFileError(path, "holds state for another nonce_prefix")
                return got

            stored = self._state.load(parse)
            self._ceiling = 0
        if stored is not None:
            self._last = self._ceiling = stored.ceiling
            self.rotations = stored.rotations
            self.nonce_prefix, self.base_prefix = stored.prefix, stored.base
        else:
            self.nonce_prefix = nonce_prefix if nonce_prefix is not None else os.urandom(PREFIX_LEN)
            self.base_prefix = self.nonce_prefix

    @property
    def last_epoch(self) -> int:
        return self._last

    def close(self) -> None:
        """Give up the state file (its lock)."""
        if self._state is not None:
            self._state.release()

    def next_epoch(self) -> int:
        """Reserve and return the next epoch (persisting a new ceiling first if needed)."""
        return self._next()[1]

    def _next(self) -> tuple[bytes, int]:
        """The (prefix, epoch) pair to seal with, taken together under the lock."""
        with self._lock:
            now = _wall_ns(self._clock)
            if self._last - now > self._max_forward_ns:
                self._rotate(now)
            epoch = max(self._last + 1, now)
            if epoch >= EPOCH_LIMIT:
                raise EpochTooFarAheadError("epoch space exhausted")
            if self._state is not None and epoch > self._ceiling:
                ceiling = min(epoch + self._reserve_ns, EPOCH_LIMIT - 1)
                self._state.save(
                    {"ceiling": ceiling, "prefix": self.nonce_prefix.hex(),
                     "base": self.base_prefix.hex(), "rotations": self.rotations}
                )  # fmt: skip
                self._ceiling = ceiling
            self._last = epoch
            return self.nonce_prefix, epoch

    def _rotate(self, now: int) -> None:
        """Leave a stream whose last epoch ran ahead of the clock (module docstring)."""
        log.warning(
            "epoch stream %s is %.1fs ahead of the clock (a forward glitch, now corrected?); "
            "rotating to a new prefix",
            self.nonce_prefix.hex(),
            (self._last - now) / 1e9,
        )
        self.nonce_prefix = successor_prefix(self.nonce_prefix)
        self.rotations += 1
        self._last = 0
        self._ceiling = 0  # forces the new prefix to be persisted before its first epoch

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
class _PrefixState:
    last: int
    recent: deque[tuple[int, bytes]] = field(
        default_factory=lambda: deque(maxlen=RECENT_PER_PREFIX)
    )


class EpochVerifier:
    """Accepts each (prefix, epoch) at most once, across restarts with ``state_file``."""

    def __init__(
        self,
        psk: bytes,
        *,
        state_file: str | os.PathLike[str] | None = None,
        max_age_s: float | None = None,
        max_forward_s: float | None = None,
        clock: Clock | None = None,
        max_prefixes: int = 4096,
        audit: AuditLog | None = None,
    ) -> None:
        self._keys = {k: derive_key(psk, k) for k in Kind}
        self._clock = resolve(clock)
        self.max_age_ns = None if max_age_s is None else int(max_age_s * 1e9)
        self.max_forward_ns = None if max_forward_s is None else int(max_forward_s * 1e9)
        self.max_prefixes = max_prefixes
        self.audit = audit
        self._lock = threading.Lock()
        self._tables: dict[Kind, dict[bytes, _PrefixState]] = {k: {} for k in Kind}
        #: successor_prefix(p) -> p for every known p: recognises a rotated sender.
        self._predecessors: dict[Kind, dict[bytes, bytes]] = {k: {} for k in Kind}
        self._floor = 0
        self.prefix_collisions = 0
        self.forward_rejections = 0
        self.rotations = 0
        self.warnings: Counter[str] = Counter()
        self._state: DurableState | None = None
        if state_file is not None:
            self._state = DurableState(Path(state_file), kind="epoch-verifier", exclusive=True)
            self._state.load(self._restore)

    def close(self) -> None:
        """Give up the state file (its lock)."""
        if self._state is not None:
            self._state.release()

    def _restore(self, data: dict[str, Any]) -> None:
        """Rebuild the tables from a state file; wrong-typed content raises TypeError."""
        self._floor = as_int(data.get("floor", 0), "floor")
        for kind in Kind:
            entries = data.get(kind.name.lower(), {})
            if not isinstance(entries, dict):
                raise TypeError(f"{kind.name.lower()} must be a table of prefix -> epoch")
            for prefix_hex, epoch in entries.items():
                prefix = as_hex(prefix_hex, "prefix", PREFIX_LEN)
                self._tables[kind][prefix] = _PrefixState(as_int(epoch, "epoch"))
                self._predecessors[kind][successor_prefix(prefix)] = prefix

    def _snapshot(self) -> dict[str, Any]:
        data: dict[str, Any] = {"floor": self._floor}
        for kind, table in self._tables.items():
            data[kind.name.lower()] = {p.hex(): s.last for p, s in table.items()}
        return data

    def last(self, prefix: bytes, kind: Kind = Kind.ANNOUNCEMENT) -> int | None:
        """The last epoch accepted from ``prefix`` (None if unknown)."""
        state = self._tables[kind].get(prefix)
        return None if state is None else state.last

    def open_ping(self, sealed: bytes) -> Announcement:
        return self.open(sealed, kind=Kind.PING)

    def open(self, sealed: bytes, *, kind: Kind = Kind.ANNOUNCEMENT) -> Announcement:
        """Verify, check freshness and order, then commit; raises a typed error otherwise."""
        prefix, epoch, payload, tag = _parse(sealed, kind)
        expected = _tag(self._keys[kind], kind, prefix, epoch, payload)
        if not hmac.compare_digest(expected, tag):
            raise AuthenticationError("announcement tag does not verify")
        self._check_time(prefix, epoch)
        digest = hashlib.sha256(payload).digest()[:16]
        rotated_from: bytes | None = None
        with self._lock:
            table = self._tables[kind]
            state = table.get(prefix)
            if state is None:
                if epoch <= self._floor:
                    raise EpochReplayError("epoch below the verifier's floor")
                if len(table) >= self.max_prefixes:
                    self._evict_oldest(kind)
                    if epoch <= self._floor:
                        raise EpochReplayError("epoch below the verifier's floor")
                rotated_from = self._predecessors[kind].get(prefix)
                if rotated_from is not None:
                    self.rotations += 1
                    self.warnings[WarningCode.EPOCH_SENDER_ROTATED] += 1
                state = table[prefix] = _PrefixState(-1)
                self._predecessors[kind][successor_prefix(prefix)] = prefix
            elif epoch <= state.last:
                self._judge_old(prefix, epoch, digest, state)
            previous = state.last
            state.last = epoch
            state.recent.append((epoch, digest))
            if self._state is not None:
                try:
                    self._state.save(self._snapshot())
                except OSError:
                    state.last = previous
                    raise
        if rotated_from is None:
            return Announcement(payload, prefix, epoch, kind)
        return self._rotated(Announcement(payload, prefix, epoch, kind), rotated_from)

    def _rotated(self, accepted: Announcement, previous: bytes) -> Announcement:
        """A sender left a stream that ran ahead of its clock: accept, count, log, audit."""
        code = WarningCode.EPOCH_SENDER_ROTATED  # counted under the lock in open()
        log.warning(
            "sender rotated from nonce_prefix %s to %s (its clock ran ahead, then was corrected)",
            previous.hex(),
            accepted.nonce_prefix.hex(),
        )
        self._audit("accepted", None, code, accepted.nonce_prefix, accepted.epoch)
        return Announcement(accepted.payload, accepted.nonce_prefix, accepted.epoch,
                            accepted.kind, str(code))  # fmt: skip

    def _audit(
        self, outcome: str, code: str | None, warning: str | None, prefix: bytes, epoch: int
    ) -> None:
        if self.audit is not None:
            self.audit.append(
                at=self._clock.wall(), outcome=outcome, code=code, warning=warning,
                msg_type=None, sender=f"epoch:{prefix.hex()}", sender_verified=True,
                msg_id=str(epoch),
            )  # fmt: skip

    def _check_time(self, prefix: bytes, epoch: int) -> None:
        if self.max_age_ns is None and self.max_forward_ns is None:
            return
        now = _wall_ns(self._clock)
        if self.max_age_ns is not None and epoch < now - self.max_age_ns:
            raise MessageStaleError("announcement older than max_age_s")
        if self.max_forward_ns is not None and epoch > now + self.max_forward_ns:
            self.forward_rejections += 1
            log.warning("authentic epoch %d is %.1fs ahead; refused", epoch, (epoch - now) / 1e9)
            self._audit("rejected", Code.EPOCH_TOO_FAR_AHEAD, None, prefix, epoch)
            raise EpochTooFarAheadError("authentic epoch jumped beyond max_forward_s")

    def _judge_old(self, prefix: bytes, epoch: int, digest: bytes, state: _PrefixState) -> None:
        """An authentic old epoch: a replay of ours, or a second sender on the same prefix."""
        known = (epoch, digest) in state.recent
        if known or not state.recent or state.last - epoch > COLLISION_HORIZON_NS:
            raise EpochReplayError(f"epoch {epoch} is not above {state.last}")
        self.prefix_collisions += 1
        log.warning(
            "nonce_prefix %s used by two senders (authentic epoch %d <= %d never accepted)",
            prefix.hex(),
            epoch,
            state.last,
        )
        raise EpochReplayError("epoch not above last: nonce_prefix collision suspected")

    def _evict_oldest(self, kind: Kind) -> None:
        table = self._tables[kind]
        oldest = min(table, key=lambda p: table[p].last)
        self._floor = max(self._floor, table.pop(oldest).last)
        self._predecessors[kind].pop(successor_prefix(oldest), None)


def _parse(sealed: bytes, kind: Kind) -> tuple[bytes, int, bytes, bytes]:
    if not isinstance(sealed, bytes):
        raise InvalidFrameError("announcement must be bytes")
    if not MIN_LEN <= len(sealed) <= MAX_LEN:
        raise InvalidFrameError(f"announcement must be {MIN_LEN}..{MAX_LEN} bytes")
    version, got_kind, prefix, epoch = _HEAD.unpack_from(sealed)
    if version != VERSION:
        raise InvalidFrameError(f"unsupported version {version}")
    if got_kind != kind:
        raise InvalidFrameError(f"expected kind {int(kind)}, got {got_kind}")
    return prefix, epoch, sealed[_HEAD.size : -TAG_LEN], sealed[-TAG_LEN:]


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


def _reseed_verifier(data: dict[str, Any] | None, now_ns: int) -> dict[str, Any]:
    """Refuse every epoch up to now: wall-anchored senders resume above it at once."""
    data = data or {}
    return {"floor": max(_int_or(data.get("floor"), 0), now_ns), "announcement": {}, "ping": {}}


register_repair("epoch-signer", _reseed_signer)
register_repair("epoch-verifier", _reseed_verifier)
