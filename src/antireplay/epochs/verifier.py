"""EpochVerifier: the driver of the epoch policy on a replay store, with audit and logs.

Theory of operation
-------------------
The verifier keeps its state in a replay store (:mod:`antireplay.state`: memory, SQLite,
Redis).  Each accepted epoch is one compare-and-advance of ``NAMESPACE:KIND:PREFIX``
(atomic on every backend, durable before ``open`` returns with SQLite or Redis), so a
restarted verifier, or another one on the same store, refuses everything accepted or
superseded.  A prefix's first accept also advances ``NAMESPACE:KIND:after:SUCCESSOR`` to
the prefix: that is how a rotated sender is recognised (``EPOCH_SENDER_ROTATED``, counted,
logged, audited once), even by a restarted verifier.  Evicting a prefix from the bounded
table raises its fence, persisted as ``NAMESPACE:KIND:floor`` in the same store step
(``forget``) that deletes the prefix's counters: the store holds at most the table's
prefixes (and their successor markers), and the floor refuses every epoch forgotten.

**Several verifiers on one store** each hold their own table, so one may evict (and
``forget``) a prefix another does not know: before a prefix it does not hold passes, a
verifier reads its counter, *then* the floor, and refuses anything at or below that
floor.  ``forget`` raises the floor and deletes the counter in one step, so a counter
read as missing because it was forgotten is always followed by a floor that covers it.
The epoch itself is then written with ``advance_above`` (one store step: above the
prefix's counter *and* the floor), which closes the race of a verifier evicting the prefix
between another's reads and its write, and refuses an epoch of a prefix it holds whose
counter another verifier forgot.  The price: after another verifier's eviction, a sender
whose clock runs behind the evicted prefix's last epoch is refused until it passes it.

**Persist, then believe.**  Every store write an accept needs (floor, successor marker,
the epoch) happens before the policy moves any mark; a failed write leaves memory as it
was, so the genuine redelivery is accepted once the store is back.

The store's own fence (a memory store's start, a lost SQLite file, a restarted Redis)
plus ``max_forward_s`` is the **restart fence**: epochs at or below it may have been
accepted by state that is gone, and are refused (``detail="restart_fence"``).
``check`` records and counts nothing; ``open`` is parse, tag (HMAC, cheap, first: what an
*authentic* old or far-ahead epoch means is counted and audited), checks, commit under a
lock.  Stored data that does not decode refuses the start (``StateFileError``) and
answers ``STATE_UNAVAILABLE`` while running.  While the fence lies ahead (:meth:`fenced`)
the driver may send :meth:`challenge` frames and feed answers to :meth:`open_answer`; a
store reporting a new fence voids every nonce and answer (they predate the loss).
"""

from __future__ import annotations

import logging
import math
import os
import threading
from collections import Counter
from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

from antireplay.audit.chain import AuditRow
from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import (
    Code,
    EpochReplayedError,
    MessageStaleError,
    SignatureInvalidError,
    StateFileError,
    StateUnavailableError,
    WarningCode,
)
from antireplay.epochs.policy import (
    LABELS,
    NONCE_LEN,
    PREFIX_LEN,
    Admission,
    Announcement,
    Claim,
    EpochPolicy,
    KeyRotation,
    Kind,
    PrefixCollision,
    Refused,
    SenderRotated,
    TooFarAhead,
    digest,
    parse,
    require_bound,
    rotation,
    successor_prefix,
    to_ns,
)
from antireplay.state import ReplayStore
from antireplay.state.memory import MemoryStore

if TYPE_CHECKING:
    from antireplay.audit import AuditLog

log = logging.getLogger("antireplay.epochs")
T = TypeVar("T")


class EpochVerifier:
    """Accepts each (prefix, epoch) at most once, on a replay store (module docstring)."""

    def __init__(
        self,
        psk: bytes,
        *,
        store: ReplayStore | None = None,
        namespace: str = "epoch",
        max_age_s: float | None = None,
        max_forward_s: float = 60.0,
        clock: Clock | None = None,
        max_prefixes: int = 4096,
        audit: AuditLog | None = None,
        rotation: KeyRotation | None = None,
    ) -> None:
        if max_age_s is not None:
            require_bound("max_age_s", max_age_s)
        require_bound("max_forward_s", max_forward_s)
        self._clock = resolve(clock)
        self.max_forward_s = max_forward_s
        self.policy = EpochPolicy(
            psk,
            max_age_ns=None if max_age_s is None else to_ns(max_age_s),
            max_forward_ns=to_ns(max_forward_s),
            max_prefixes=max_prefixes,
            rotation=rotation,
        )
        self.audit = audit
        self.namespace = namespace
        #: ``NAMESPACE:KIND:`` per kind, built once (an enum's ``name`` is a property call).
        self._keys = {kind: f"{namespace}:{kind.name.lower()}:" for kind in Kind}
        self._owns_store = store is None  # the caller that opened a store closes it
        self.store: ReplayStore = (
            MemoryStore(max_entries=1, clock=self._clock) if store is None else store
        )
        self._lock = threading.Lock()
        self.prefix_collisions = 0
        self.forward_rejections = 0
        self.rotations = 0
        self.warnings: Counter[WarningCode] = Counter()
        self._fence_seen, self._restart_ns = -math.inf, -1
        #: The prefix this verifier's challenges carry (random per run; names the asker).
        self.challenger = os.urandom(PREFIX_LEN)
        self.store.verify()  # loss detection now: a lost store raises its fence
        for kind, table in self.policy.tables.items():  # undecodable: StateFileError, no start
            table.raise_fence(self.store.current(self._key(kind, "floor")) or -1)

    @property
    def max_prefixes(self) -> int:
        return self.policy.tables[Kind.ANNOUNCEMENT].max_keys

    def close(self) -> None:
        """Close the store if this verifier made it (the in-memory default)."""
        if self._owns_store:
            self.store.close()

    def _key(self, kind: Kind, name: str) -> str:
        return self._keys[kind] + name

    def restart_fence(self) -> int:
        """Epochs at or below this may have been accepted by a run whose state the store
        lost (or by a previous process, for the memory store): the store's fence plus
        ``max_forward_s``, the furthest ahead any sender could have been.  -1: none."""
        fence = self.store.fence()
        if fence != self._fence_seen:  # rare: computed once per fence the store reports
            self._fence_seen = fence
            self._restart_ns = to_ns(fence + self.max_forward_s)
            self.policy.forget_answers()  # answers given before a loss prove nothing after it
        return self._restart_ns

    def fenced(self) -> bool:
        """Whether the restart fence still lies ahead: only then is a challenge worth sending."""
        return self._now() <= self.restart_fence()

    def challenge(self) -> bytes | None:
        """A sealed challenge with a new random nonce while :meth:`fenced` (else None);
        at most ``OUTSTANDING`` nonces are held, the oldest dropped first."""
        if not self.fenced():
            return None
        with self._lock:
            return self.policy.challenge(os.urandom(NONCE_LEN), self.challenger, self._now())

    def open_answer(self, sealed: bytes) -> Announcement:
        """Check (shape, a nonce outstanding), authenticate, commit a signer's answer: from
        now on its prefix's epochs above the answered one pass the restart fence."""
        claim = parse(sealed, Kind.ANSWER)
        self.restart_fence()  # a store that lost state since the challenge voids its nonces
        self._judge(self.policy.check_answer(claim))
        if not self._judge(self.policy.authentic(claim)):
            raise SignatureInvalidError("answer tag does not verify")
        with self._lock:
            self._judge(self.policy.check_answer(claim))
            self.policy.commit_answer(claim)
        log.info("prefix %s answered a challenge: its epochs above %d are fresh",
                 claim.prefix.hex(), claim.epoch)  # fmt: skip
        return Announcement(claim.payload, claim.prefix, claim.epoch, Kind.ANSWER)

    def last(self, prefix: bytes, kind: Kind = Kind.ANNOUNCEMENT) -> int | None:
        """The last epoch committed from ``prefix`` (None if unknown)."""
        mark = self.policy.last(kind, prefix)
        return mark if mark is not None else self._current(self._key(kind, prefix.hex()))

    def open_ping(self, sealed: bytes) -> Announcement:
        return self.open(sealed, kind=Kind.PING)

    def check(self, sealed: bytes, *, kind: Kind = Kind.ANNOUNCEMENT) -> None:
        """Raise the typed reason ``sealed`` would be refused, the MAC aside; records
        nothing and counts nothing (an unauthenticated frame carries no evidence)."""
        claim = parse(sealed, kind)
        self._judge(self.policy.check_time(claim, self._now(), self.restart_fence(),
                                           authentic=False))  # fmt: skip
        with self._lock:
            self._order(claim, b"", authentic=False)

    def open(self, sealed: bytes, *, kind: Kind = Kind.ANNOUNCEMENT) -> Announcement:
        """The recipe: parse, authenticate (HMAC, cheap), check, commit; raises a typed
        error otherwise.  The MAC runs before the order check because what an *authentic*
        old or far-ahead epoch means (a collision, a glitch) is counted and audited."""
        claim = parse(sealed, kind)
        if not self._judge(self.policy.authentic(claim)):
            raise SignatureInvalidError(f"{LABELS[kind]} tag does not verify")
        self._judge(self.policy.check_time(claim, self._now(), self.restart_fence(),
                                           authentic=True))  # fmt: skip
        seen = digest(claim.payload)
        with self._lock:
            unseen = self._order(claim, seen, authentic=True)
            admission = self._judge(self.policy.admit(claim))
            rotated = self._commit(claim, seen, unseen, admission)
        accepted = Announcement(claim.payload, claim.prefix, claim.epoch, kind)
        return accepted if rotated is None else self._rotated(accepted, rotated)

    def _now(self) -> int:
        return to_ns(self._clock.wall())

    def _order(self, claim: Claim, seen: bytes, *, authentic: bool) -> bool:
        """The policy's order check, with the store's epoch for a prefix the table does
        not hold (caller holds the lock).  True: the store holds none for it."""
        held = self._judge(self.policy.held(claim))
        stored = None
        if not held:  # the counter, then the floor: see "Several verifiers" above
            stored = self._current(self._key(claim.kind, claim.prefix.hex()))
            floor = self._current(self._key(claim.kind, "floor"))
            if floor is not None:
                self.policy.tables[claim.kind].raise_fence(floor)
                self._judge(self.policy.held(claim))
        return self._judge(self.policy.check_order(claim, seen, stored, authentic=authentic))

    def _commit(
        self, claim: Claim, seen: bytes, unseen: bool, admission: Admission
    ) -> SenderRotated | None:
        """Persist, then believe (caller holds the lock): the raised floor, a new prefix's
        successor marker and the epoch reach the store before the policy moves a mark."""
        kind, prefix, epoch = claim.kind, claim.prefix, claim.epoch
        before = None
        if admission.new and unseen:  # read before any write: a failed read changes nothing
            before = self._current(self._key(kind, "after:" + prefix.hex()))
        if admission.floor is not None:
            self._forget(kind, admission.evicted, admission.floor)
        if admission.new:
            self._write(self._key(kind, "after:" + successor_prefix(prefix).hex()),
                        int.from_bytes(prefix, "big"))  # fmt: skip
        fenced = self._key(kind, prefix.hex()), epoch, self._key(kind, "floor")
        if not self._store_op(lambda: self.store.advance_above(*fenced)):
            raise EpochReplayedError(
                f"epoch {epoch} already committed to the shared state, or at or below its floor"
            )
        if epoch <= self.policy.fence_for(prefix, self.restart_fence()):  # the advance noticed loss
            raise MessageStaleError("the verifier's store lost state", detail="restart_fence")
        self.policy.commit(claim, seen)
        event = rotation(claim, admission, unseen, before)
        if event is not None:
            self.rotations += 1
            self.warnings[WarningCode.EPOCH_SENDER_ROTATED] += 1
        return event

    def _forget(self, kind: Kind, evicted: bytes | None, floor: int) -> None:
        """Raise the floor and drop the evicted prefix's counters in one store step: its
        epoch, the marker naming it and the marker it left for its successor (a rotation
        to that successor is then no longer recognised; the floor refuses every epoch the
        prefix had)."""
        keys = [] if evicted is None else [
            self._key(kind, name)
            for name in (evicted.hex(), "after:" + evicted.hex(),
                         "after:" + successor_prefix(evicted).hex())
        ]  # fmt: skip
        floor_key = self._key(kind, "floor")
        self._store_op(lambda: self.store.forget(keys, floor_key, floor))

    def _current(self, key: str) -> int | None:
        return self._store_op(lambda: self.store.current(key))

    def _write(self, key: str, value: int) -> bool:
        return self._store_op(lambda: self.store.advance(key, value))

    @staticmethod
    def _store_op(op: Callable[[], T]) -> T:
        """A store call while running: stored data that does not decode is 503, naming
        the store and the recovery (at start it refuses the start instead)."""
        try:
            return op()
        except StateFileError as exc:
            raise StateUnavailableError(str(exc)) from None

    def _judge(self, result: Refused | T) -> T:
        """Report a refusal's evidence (count, log, audit) and raise its error."""
        if not isinstance(result, Refused):
            return result
        event = result.event
        if isinstance(event, TooFarAhead):
            self.forward_rejections += 1
            log.warning("authentic epoch %d is %.1fs ahead", event.epoch, event.ahead_ns / 1e9)
            self._audit("rejected", Code.EPOCH_TOO_FAR_AHEAD, None, event.prefix, event.epoch)
        elif isinstance(event, PrefixCollision):
            self.prefix_collisions += 1
            log.warning(
                "nonce_prefix %s used by two senders (authentic epoch %d <= %d never accepted)",
                event.prefix.hex(),
                event.epoch,
                event.last,
            )
        raise result.error

    def _rotated(self, accepted: Announcement, event: SenderRotated) -> Announcement:
        """A sender left a stream that ran ahead of its clock: accept, log, audit."""
        code = WarningCode.EPOCH_SENDER_ROTATED  # counted under the lock in _commit()
        log.warning(
            "sender rotated from nonce_prefix %s to %s (its clock ran ahead, then was corrected)",
            event.previous.hex(),
            event.prefix.hex(),
        )
        self._audit("accepted", None, code, event.prefix, event.epoch)
        return Announcement(accepted.payload, accepted.nonce_prefix, accepted.epoch,
                            accepted.kind, code)  # fmt: skip

    def _audit(
        self, outcome: str, code: str | None, warning: str | None, prefix: bytes, epoch: int
    ) -> None:
        if self.audit is not None:
            self.audit.append(
                AuditRow(self._clock.wall(), outcome, code, warning, sender=f"epoch:{prefix.hex()}",
                         sender_verified=True, msg_id=str(epoch))
            )  # fmt: skip
