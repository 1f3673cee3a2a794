"""EpochSigner: seals with strictly increasing, wall-anchored epochs that survive a crash.

Theory of operation
-------------------
``epoch = max(last + 1, wall_ns)`` from one wall-anchored
:class:`~antireplay.core.counters.NonceCounter`: strictly increasing, never below the current
time, so a verifier that never heard of a sender can still refuse a capture older than
its ``max_age_s``, and a clock stepping back never makes epochs regress.

A clock that jumped ahead for one seal and was then corrected would leave ``last + 1`` far
ahead, locking the sender out of every verifier's ``max_forward_s``.  So before each seal
the signer compares ``last`` with the clock; more than its own ``max_forward_s`` ahead (at
or below the verifiers', above ``reserve_s``), it **rotates** to
:func:`~antireplay.epochs.policy.successor_prefix` and restarts the stream at the current
time.  No epoch repeats or drops within a prefix; the old prefix is never used again.

With ``state`` (a :class:`~antireplay.state.durable.DurableState` its caller built with
:func:`signer_state`) the signer reserves ``reserve_s`` of epochs at a time (one fsync a
second for a busy sender) before emitting any of them, so after a crash it starts above
anything it could have sent.  The file records the current prefix, the one it started from
(``base``, which ``nonce_prefix`` or ``service_name`` must match) and the rotation count; a
rotation is saved before its first epoch.  The file has one owner (an OS lock): two signers
on it would repeat epochs.  :meth:`EpochSigner.answer` answers a fresh verifier's challenge
at the next epoch.  With a ``rotation`` (:class:`~antireplay.epochs.policy.KeyRotation`) every
epoch after the cut-over is sealed with the fleet key's successor.
"""

from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from antireplay.core.clock import Clock, resolve
from antireplay.core.counters import NonceCounter
from antireplay.core.errors import (
    InvalidFrameError,
    MessageStaleError,
    SignatureInvalidError,
    StateFileError,
)
from antireplay.epochs.policy import (
    EPOCH_LIMIT,
    NONCE_LEN,
    PREFIX_LEN,
    KeyRing,
    KeyRotation,
    Kind,
    Refused,
    parse,
    prefix_for_service,
    require_size,
    seal,
    successor_prefix,
    to_ns,
)
from antireplay.state.ceilings import counter_on_state
from antireplay.state.durable import DurableState, as_hex, as_int, register_repair

log = logging.getLogger("antireplay.epochs")
#: The kind a signer's state file records (and ``antireplay state repair`` knows).
STATE_KIND = "epoch-signer"


def signer_state(path: str | os.PathLike[str]) -> DurableState:
    """The signer's state file at ``path``, not yet read: one owner (an OS lock), checksum,
    generation and rollback witness (:mod:`antireplay.state.durable`)."""
    return DurableState(Path(path), kind=STATE_KIND, exclusive=True)


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
        state: DurableState | None = None,
        clock: Clock | None = None,
        reserve_s: float = 1.0,
        max_forward_s: float = 60.0,
        rotation: KeyRotation | None = None,
    ) -> None:
        if nonce_prefix is not None and service_name is not None:
            raise ValueError("give nonce_prefix or service_name, not both")
        if service_name is not None:
            nonce_prefix = prefix_for_service(service_name)
        if nonce_prefix is not None and len(nonce_prefix) != PREFIX_LEN:
            raise ValueError(f"nonce_prefix must be {PREFIX_LEN} bytes")
        if not max_forward_s > reserve_s:
            raise ValueError("max_forward_s must exceed reserve_s (else every restart rotates)")
        self._ring = KeyRing(psk, rotation)
        self._clock = clock = resolve(clock)
        self._max_forward_ns = int(max_forward_s * 1_000_000_000)
        self._lock = threading.Lock()
        self.rotations = 0
        self.nonce_prefix = nonce_prefix if nonce_prefix is not None else os.urandom(PREFIX_LEN)
        self.base_prefix = self.nonce_prefix

        def anchor() -> int:
            return to_ns(clock.wall())

        if state is None:
            self._epochs = NonceCounter(1, limit=EPOCH_LIMIT, anchor=anchor)
            return
        if state.kind != STATE_KIND or not state.exclusive:
            raise ValueError(f"an epoch signer's state is exclusive, of kind {STATE_KIND!r}")
        wanted, path = nonce_prefix, str(state.path)

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
            ahead = self._epochs.last - to_ns(self._clock.wall())
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
        require_size(payload)  # before an epoch is spent on it
        prefix, epoch = self._next()
        return seal(self._ring.sealing(epoch)[kind], kind, prefix, epoch, payload)

    def seal_ping(self, payload: bytes) -> bytes:
        """A binding ping: same discipline, separate key."""
        return self.seal(payload, kind=Kind.PING)

    def answer(self, challenge: bytes) -> bytes:
        """The answer to a fresh verifier's challenge: its nonce sealed at this signer's
        next (prefix, epoch), above everything sealed before.  Cheap checks (shape, the
        challenge's time within ``max_forward_s`` of ours) before the MAC; a refused
        challenge raises its typed error and spends no epoch."""
        claim = parse(challenge, Kind.CHALLENGE)
        if len(claim.payload) != NONCE_LEN:
            raise InvalidFrameError(f"a challenge carries a {NONCE_LEN}-byte nonce")
        if abs(claim.epoch - to_ns(self._clock.wall())) > self._max_forward_ns:
            raise MessageStaleError("challenge not sent within max_forward_s of now")
        verified = self._ring.verify(claim)
        if isinstance(verified, Refused):
            raise verified.error
        if not verified:
            raise SignatureInvalidError("challenge tag does not verify")
        return self.seal(claim.payload, kind=Kind.ANSWER)


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


register_repair(STATE_KIND, _reseed_signer)
