"""ReplayCache: the §8.3 window over a store, in two phases (check records nothing, commit records).

Theory of operation
-------------------
The window policy (:class:`~antireplay.core.window.Window`) is pure; a store
(:mod:`antireplay.state`) keeps the seen-set and its safety state.  This
module is the caller that joins them, the one the pipeline runs and the one an
embedder uses directly:

* :meth:`ReplayCache.check` plans the message (shape, staleness, future) and
  judges what this process knows of its msg_id.  It records nothing in the
  store, so a receiver runs it before any cryptography and throws replays away
  cheaply (see *The index* for what it reads).
* :meth:`ReplayCache.commit` plans again on a fresh ``now``, refuses what the
  store's last known fence and watermark already refuse (so a refused message
  does not spend its msg_id), performs the store's one atomic ``commit``
  (which also notices data loss) and judges what it returned.  Run it only
  after the message authenticated; of two racers on one msg_id exactly one is
  admitted.  :meth:`ReplayCache.commit_async` is the same two halves around the
  store's ``commit_async``, for an event loop.
* ``try_check`` and ``try_commit`` are the same with a refusal *returned* (a
  :class:`~antireplay.core.window.Refusal` value; ``error()`` builds its exception):
  a refusal is an answer, and building and raising an exception costs more than an
  admission.

**The index** (a store other than process memory).  ``check`` must not cost a
store read for every fresh command, so the cache keeps a bounded in-memory index
(a :class:`MemoryStore` of ``max_size`` entries, no fence) of the msg_ids this
cache's commits recorded or found live in the store, each to the expiry the store
holds.  ``check`` answers from it: a hit is a replay; a miss proceeds to
authentication without I/O, because ``commit`` is authoritative and refuses a
replay the index does not know (one committed by another process sharing the
store, or by this process before a restart); that costs one signature check per
process per msg_id, after which the refusing commit indexes it.  The index
forgets nothing silently: an entry leaves it only by expiry or, the index full,
by eviction that raises its watermark, and a miss expiring at or below that
watermark (this cache may have forgotten its own commit) reads the store:
``check``'s only I/O, possible only after more than ``max_size`` live msg_ids
in one window.  So ``check`` costs two dict lookups (~0.3 µs, no lock held, no
thread needed) except in that case.  On the memory store the store itself is
the index (its ``lookup`` is a dict read).

No lock is held here: the store's commit is the only atomic step.  A store that
cannot be reached fails closed (``STATE_UNAVAILABLE``, 503) for everything
except a fresh ESTOP, which is admitted with ``warning="STATE_UNAVAILABLE"``
(:func:`~antireplay.core.window.estop_survives`, the rule for every outage).

Without a ``store`` the cache uses a :class:`~antireplay.state.memory.MemoryStore`
bounded by ``max_size``, with its restart fence: a new process refuses anything
stamped at or before its start (plus skew), which the previous process might
have accepted.

Refusals are counted by cause in :attr:`ReplayCache.refusals` (``restart_fence``,
``watermark``, ``saturated``, the codes) and data-loss detections in
:attr:`ReplayCache.losses`, for metrics; ``on_loss`` lets the pipeline audit them.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from typing import SupportsFloat, SupportsIndex

from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import ConfigError, ReplayAttackError, StateUnavailableError
from antireplay.core.messages import MessageType
from antireplay.core.settings import ALLOWED, SecurityConfig
from antireplay.core.window import NEVER, Refusal, Seen, Verdict, Window, estop_survives
from antireplay.state import Offload, ReplayStore
from antireplay.state.memory import MemoryStore

_STATE_UNAVAILABLE = "STATE_UNAVAILABLE"


class ReplayCache:
    """The window over a store: ``check`` (records nothing), then ``commit`` (records)."""

    def __init__(
        self,
        window_s: SupportsFloat = 30.0,
        max_size: SupportsIndex = 10_000,
        skew_s: SupportsFloat = 5.0,
        clock: Clock | None = None,
        *,
        safety_window_s: SupportsFloat = 10.0,
        store: ReplayStore | None = None,
    ) -> None:
        if isinstance(max_size, bool) or not isinstance(max_size, int):
            raise ConfigError("max_size", max_size, ALLOWED["msg_id_cache_size"])
        SecurityConfig.from_mapping({"msg_id_cache_size": max_size})  # range, as in YAML
        self.policy = Window(window_s, skew_s, safety_window_s)
        self.clock = resolve(clock)
        self.store: ReplayStore = (
            store if store is not None else MemoryStore(max_entries=max_size, clock=self.clock)
        )
        # The memory store, called natively; else the index in front of the store.
        self._memory: MemoryStore | None = (
            self.store if isinstance(self.store, MemoryStore) else None
        )
        self._index: MemoryStore | None = (
            None
            if self._memory is not None
            else MemoryStore(max_entries=max_size, restart_fence=False)
        )
        self.refusals: Counter[str] = Counter()
        self.losses = 0
        #: Called with a reason when a commit finds the store lost state (the pipeline audits it).
        self.on_loss: Callable[[str], None] | None = None

    @classmethod
    def from_config(
        cls, config: SecurityConfig, clock: Clock | None = None, store: ReplayStore | None = None
    ) -> ReplayCache:
        """Build a cache from a validated ``security:`` block."""
        return cls(
            config.replay_window_s,
            config.msg_id_cache_size,
            config.skew_s,
            clock,
            safety_window_s=config.safety_window_s,
            store=store,
        )

    @property
    def window_s(self) -> float:
        return self.policy.window_s

    def window_for(self, msg_type: int) -> float:
        return self.policy.window_for(msg_type)

    def __len__(self) -> int:
        return int(self.store.status()["entries"])

    def check(
        self,
        msg_id: object,
        timestamp: object,
        msg_type: int = MessageType.COMMAND,
        safety_event: str | None = None,
    ) -> Verdict:
        """Apply every rule to what this process knows of the msg_id; record nothing
        (see *The index* in the module docstring for what that costs)."""
        return _raised(self.try_check(msg_id, timestamp, msg_type, safety_event))

    def try_check(
        self,
        msg_id: object,
        timestamp: object,
        msg_type: int = MessageType.COMMAND,
        safety_event: str | None = None,
    ) -> Verdict | Refusal:
        """:meth:`check` with a refusal returned, not raised."""
        now = self.clock.wall()
        try:
            plan = self.policy.plan_or_refusal(msg_id, timestamp, msg_type, safety_event, now)
        except ReplayAttackError as exc:  # a malformed msg_id or timestamp
            return self._refused(Refusal.of(exc))
        if isinstance(plan, Refusal):
            return self._refused(plan)
        seen: Seen | StateUnavailableError
        memory, index = self._memory, self._index
        if memory is not None:
            seen = memory.lookup(plan.msg_id)
        elif index is not None:
            seen = self._indexed(plan, index, now)
        else:  # pragma: no cover - one of the two is always set
            seen = self.store.lookup(plan.msg_id)
        return self._decided(plan, now, seen)

    def _indexed(
        self, plan: Verdict, index: MemoryStore, now: float
    ) -> Seen | StateUnavailableError:
        """What the index knows of ``plan``'s msg_id, with the store's last known fence and
        watermark; the store itself only where the index may have forgotten (see above)."""
        expiry = index.expiry_of(plan.msg_id)
        store = self.store
        if expiry < now and plan.expires_at <= index.watermark():
            try:
                return store.lookup(plan.msg_id)
            except StateUnavailableError as exc:
                return exc
        return Seen(expiry, store.watermark(), store.fence())

    def commit(
        self,
        msg_id: object,
        timestamp: object,
        msg_type: int = MessageType.COMMAND,
        safety_event: str | None = None,
    ) -> Verdict:
        """Apply every rule and atomically record the msg_id (after authentication)."""
        return _raised(self.try_commit(msg_id, timestamp, msg_type, safety_event))

    def try_commit(
        self,
        msg_id: object,
        timestamp: object,
        msg_type: int = MessageType.COMMAND,
        safety_event: str | None = None,
    ) -> Verdict | Refusal:
        """:meth:`commit` with a refusal returned, not raised."""
        now = self.clock.wall()
        plan = self._plan(msg_id, timestamp, msg_type, safety_event, now)
        if isinstance(plan, Refusal):
            return plan
        memory = self._memory
        if memory is not None:  # process memory: no outage, no loss, no index, no Seen
            expiry, watermark, recorded, full = memory.commit_fields(
                plan.msg_id, plan.expires_at, now, plan.estop
            )
            verdict = self.policy.decide(
                plan, expiry, watermark, memory.fence(), recorded, full, now
            )
            return self._refused(verdict) if isinstance(verdict, Refusal) else verdict
        seen: Seen | StateUnavailableError
        try:
            seen = self.store.commit(plan.msg_id, plan.expires_at, now, plan.estop)
        except StateUnavailableError as exc:
            seen = exc
        return self._finish(plan, now, seen)

    async def commit_async(
        self,
        msg_id: object,
        timestamp: object,
        msg_type: int = MessageType.COMMAND,
        safety_event: str | None = None,
        offload: Offload | None = None,
    ) -> Verdict:
        """:meth:`commit` for an event loop: the store's ``commit_async`` is awaited
        between the same two halves (a blocking store's runs in ``offload``)."""
        plan, now = self.begin_commit(msg_id, timestamp, msg_type, safety_event)
        seen: Seen | StateUnavailableError
        try:
            seen = await self.store.commit_async(
                plan.msg_id, plan.expires_at, now, plan.estop, offload
            )
        except StateUnavailableError as exc:
            seen = exc
        return self.finish_commit(plan, now, seen)

    def begin_commit(
        self,
        msg_id: object,
        timestamp: object,
        msg_type: int = MessageType.COMMAND,
        safety_event: str | None = None,
    ) -> tuple[Verdict, float]:
        """:meth:`commit` up to the store's: the plan on a fresh ``now`` (both returned, for
        the store's ``commit(plan.msg_id, plan.expires_at, now, plan.estop)`` and
        :meth:`finish_commit`), refusing what the known fence or watermark already refuses
        *before* recording it: a refused message must not spend its msg_id.  :meth:`commit`
        and :meth:`commit_async` perform the store's commit between the halves."""
        now = self.clock.wall()
        return _raised(self._plan(msg_id, timestamp, msg_type, safety_event, now)), now

    def finish_commit(
        self, plan: Verdict, now: float, seen: Seen | StateUnavailableError
    ) -> Verdict:
        """:meth:`commit` after the store's: judge what its atomic commit returned, or the
        error it raised."""
        return _raised(self._finish(plan, now, seen))

    def _plan(
        self, msg_id: object, timestamp: object, msg_type: int, safety_event: str | None, now: float
    ) -> Verdict | Refusal:
        """The plan, refused already where the known fence or watermark refuses it."""
        policy = self.policy
        try:
            plan = policy.plan_or_refusal(msg_id, timestamp, msg_type, safety_event, now)
        except ReplayAttackError as exc:  # a malformed msg_id or timestamp
            return self._refused(Refusal.of(exc))
        if isinstance(plan, Refusal):
            return self._refused(plan)
        memory = self._memory
        if memory is not None:
            watermark, fence = memory.watermark(), memory.fence()
        else:
            store = self.store
            watermark, fence = store.watermark(), store.fence()
        known = policy.decide(plan, NEVER, watermark, fence, False, False, now)
        if isinstance(known, Refusal):
            return self._refused(known)
        return plan

    def _finish(
        self, plan: Verdict, now: float, seen: Seen | StateUnavailableError
    ) -> Verdict | Refusal:
        index = self._index
        if index is not None and isinstance(seen, Seen):
            # Persist, then believe: the store's commit returned, so its entry stands.
            expiry = seen.expiry
            if seen.recorded or (plan.estop and plan.expires_at > expiry):
                expiry = plan.expires_at
            if expiry >= now:
                index.commit(plan.msg_id, expiry, now, True)
        return self._decided(plan, now, seen)

    def _decided(
        self, plan: Verdict, now: float, seen: Seen | StateUnavailableError
    ) -> Verdict | Refusal:
        if isinstance(seen, StateUnavailableError):
            warning = estop_survives(plan.estop, plan.warning, _STATE_UNAVAILABLE)
            if warning is None:
                return self._refused(Refusal.of(seen))
            return Verdict(
                plan.msg_id, plan.timestamp, plan.window_s, plan.expires_at, warning, True
            )
        if seen.lost:
            self.losses += 1
            if self.on_loss is not None:
                reason = getattr(self.store, "loss_reason", None)
                said = f"{self.store.backend} lost or replaced its state; fence raised"
                self.on_loss(str(reason) if reason else said)
        verdict = self.policy.decide(
            plan, seen.expiry, seen.watermark, seen.fence, seen.recorded, seen.full, now
        )
        if isinstance(verdict, Refusal):
            return self._refused(verdict)
        return verdict

    def _refused(self, refusal: Refusal) -> Refusal:
        self.refusals[refusal.count_key] += 1
        return refusal


def _raised(outcome: Verdict | Refusal) -> Verdict:
    """The verdict, or its refusal raised (the raising API over the ``try_`` forms)."""
    if isinstance(outcome, Refusal):
        raise outcome.error()
    return outcome
