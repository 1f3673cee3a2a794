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

**Crash safety.**  With ``state_file`` the signer persists a reserved ceiling
through :mod:`antireplay.durable` before emitting any epoch above the previous
one, reserving ``reserve_s`` (default 1 s) of epochs at a time, so a busy
sender fsyncs about once a second, not per message.  After a crash or a host
reboot it starts above the ceiling, above anything it could have sent.  Choose
``max_forward_s`` at verifiers larger than ``reserve_s``.

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
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any

from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from antireplay.clock import Clock, resolve
from antireplay.durable import DurableState, register_repair
from antireplay.errors import (
    AuthenticationError,
    EpochReplayError,
    EpochTooFarAheadError,
    InvalidFrameError,
    MessageStaleError,
    StateFileError,
)

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


def derive_key(psk: bytes, kind: Kind) -> bytes:
    """HKDF-SHA256 with a fixed label per kind."""
    if not isinstance(psk, bytes) or len(psk) < 16:
        raise ValueError("psk must be at least 16 bytes")
    info = b"antireplay/v1 epoch " + _LABELS[kind].encode()
    return HKDF(algorithm=hashes.SHA256(), length=32, salt=None, info=info).derive(psk)


def prefix_for_service(service_name: str) -> bytes:
    """The nonce prefix of a named discovery service (names must be unique!)."""
    return hashlib.sha256(b"antireplay/v1 prefix" + service_name.encode()).digest()[:PREFIX_LEN]


def _tag(key: bytes, kind: Kind, prefix: bytes, epoch: int, payload: bytes) -> bytes:
    trailer = prefix + epoch.to_bytes(8, "big") + bytes([VERSION, kind])
    return hmac.digest(key, payload + trailer, "sha256")


def _wall_ns(clock: Clock) -> int:
    return int(clock.wall() * 1_000_000_000)


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
    ) -> None:
        if nonce_prefix is not None and service_name is not None:
            raise ValueError("give nonce_prefix or service_name, not both")
        if service_name is not None:
            nonce_prefix = prefix_for_service(service_name)
        if nonce_prefix is not None and len(nonce_prefix) != PREFIX_LEN:
            raise ValueError(f"nonce_prefix must be {PREFIX_LEN} bytes")
        self._keys = {k: derive_key(psk, k) for k in Kind}
        self._clock = resolve(clock)
        self._reserve_ns = int(reserve_s * 1_000_000_000)
        self._lock = threading.Lock()
        self._last = 0
        self._ceiling = EPOCH_LIMIT
        self._state: DurableState | None = None
        if state_file is not None:
            self._state = DurableState(Path(state_file), kind="epoch-signer")
            data = self._state.load()
            if data is not None:
                stored = bytes.fromhex(str(data["prefix"]))
                if nonce_prefix is not None and stored != nonce_prefix:
                    raise StateFileError(str(state_file), "holds state for another nonce_prefix")
                nonce_prefix, self._last = stored, int(data["ceiling"])
            self._ceiling = self._last
        self.nonce_prefix = nonce_prefix if nonce_prefix is not None else os.urandom(PREFIX_LEN)

    @property
    def last_epoch(self) -> int:
        return self._last

    def next_epoch(self) -> int:
        """Reserve and return the next epoch (persisting a new ceiling first if needed)."""
        with self._lock:
            epoch = max(self._last + 1, _wall_ns(self._clock))
            if epoch >= EPOCH_LIMIT:
                raise EpochTooFarAheadError("epoch space exhausted")
            if self._state is not None and epoch > self._ceiling:
                ceiling = min(epoch + self._reserve_ns, EPOCH_LIMIT - 1)
                self._state.save({"ceiling": ceiling, "prefix": self.nonce_prefix.hex()})
                self._ceiling = ceiling
            self._last = epoch
            return epoch

    def seal(self, payload: bytes, *, kind: Kind = Kind.ANNOUNCEMENT) -> bytes:
        """Seal one announcement (or, with ``kind=Kind.PING``, one binding ping)."""
        if len(payload) + MIN_LEN > MAX_LEN:
            raise ValueError("payload too large")
        epoch = self.next_epoch()
        head = _HEAD.pack(VERSION, kind, self.nonce_prefix, epoch)
        return head + payload + _tag(self._keys[kind], kind, self.nonce_prefix, epoch, payload)

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
    ) -> None:
        self._keys = {k: derive_key(psk, k) for k in Kind}
        self._clock = resolve(clock)
        self.max_age_ns = None if max_age_s is None else int(max_age_s * 1e9)
        self.max_forward_ns = None if max_forward_s is None else int(max_forward_s * 1e9)
        self.max_prefixes = max_prefixes
        self._lock = threading.Lock()
        self._tables: dict[Kind, dict[bytes, _PrefixState]] = {k: {} for k in Kind}
        self._floor = 0
        self.prefix_collisions = 0
        self.forward_rejections = 0
        self._state: DurableState | None = None
        if state_file is not None:
            self._state = DurableState(Path(state_file), kind="epoch-verifier")
            data = self._state.load()
            if data is not None:
                self._restore(data)

    def _restore(self, data: dict[str, Any]) -> None:
        self._floor = int(data.get("floor", 0))
        for kind in Kind:
            for prefix_hex, epoch in dict(data.get(kind.name.lower(), {})).items():
                self._tables[kind][bytes.fromhex(prefix_hex)] = _PrefixState(int(epoch))

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
        self._check_time(epoch)
        digest = hashlib.sha256(payload).digest()[:16]
        with self._lock:
            table = self._tables[kind]
            state = table.get(prefix)
            if state is None:
                if epoch <= self._floor:
                    raise EpochReplayError("epoch below the verifier's floor")
                if len(table) >= self.max_prefixes:
                    self._evict_oldest(table)
                    if epoch <= self._floor:
                        raise EpochReplayError("epoch below the verifier's floor")
                state = table[prefix] = _PrefixState(-1)
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
        return Announcement(payload, prefix, epoch, kind)

    def _check_time(self, epoch: int) -> None:
        if self.max_age_ns is None and self.max_forward_ns is None:
            return
        now = _wall_ns(self._clock)
        if self.max_age_ns is not None and epoch < now - self.max_age_ns:
            raise MessageStaleError("announcement older than max_age_s")
        if self.max_forward_ns is not None and epoch > now + self.max_forward_ns:
            self.forward_rejections += 1
            log.warning("authentic epoch %d is %.1fs ahead; refused", epoch, (epoch - now) / 1e9)
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

    def _evict_oldest(self, table: dict[bytes, _PrefixState]) -> None:
        oldest = min(table, key=lambda p: table[p].last)
        self._floor = max(self._floor, table.pop(oldest).last)


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
    prefix = data.get("prefix")
    if not (isinstance(prefix, str) and len(prefix) == 2 * PREFIX_LEN):
        prefix = os.urandom(PREFIX_LEN).hex()
    return {"ceiling": max(_int_or(data.get("ceiling"), 0), now_ns), "prefix": prefix}


def _reseed_verifier(data: dict[str, Any] | None, now_ns: int) -> dict[str, Any]:
    """Refuse every epoch up to now: wall-anchored senders resume above it at once."""
    data = data or {}
    return {"floor": max(_int_or(data.get("floor"), 0), now_ns), "announcement": {}, "ping": {}}


register_repair("epoch-signer", _reseed_signer)
register_repair("epoch-verifier", _reseed_verifier)
