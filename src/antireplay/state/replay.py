"""ReplayCache: the §8.3 window over a store, in two phases (check records nothing, commit records).

Theory of operation
-------------------
The window policy (:class:`~antireplay.core.window.Window`) is pure; a store
(:mod:`antireplay.state`) keeps the seen-set and its safety state.  This
module is the caller that joins them, the one the pipeline runs and the one an
embedder uses directly:

* :meth:`ReplayCache.check` plans the message (shape, staleness, future), reads
  the store's entry with ``lookup`` and judges it.  It records nothing, so a
  receiver runs it before any cryptography and throws replays away cheaply.
* :meth:`ReplayCache.commit` plans again on a fresh ``now``, refuses what the
  store's last known fence and watermark already refuse (so a refused message
  does not spend its msg_id), performs the store's one atomic ``commit``
  (which also notices data loss) and judges what it returned.  Run it only
  after the message authenticated; of two racers on one msg_id exactly one is
  admitted.  :meth:`ReplayCache.commit_async` is the same two halves around the
  store's ``commit_async``, for an event loop.

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
from antireplay.core.window import NEVER, Seen, Verdict, Window, estop_survives
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
        """Apply every rule to what the store holds now; record nothing."""
        now = self.clock.wall()
        try:
            plan = self.policy.plan(msg_id, timestamp, msg_type, safety_event, now)
            seen: Seen | StateUnavailableError
            try:
                seen = self.store.lookup(plan.msg_id)
            except StateUnavailableError as exc:
                seen = exc
            return self._judge(plan, now, seen)
        except ReplayAttackError as exc:
            self.refusals[exc.detail or exc.code] += 1
            raise

    def commit(
        self,
        msg_id: object,
        timestamp: object,
        msg_type: int = MessageType.COMMAND,
        safety_event: str | None = None,
    ) -> Verdict:
        """Apply every rule and atomically record the msg_id (after authentication)."""
        plan, now = self.begin_commit(msg_id, timestamp, msg_type, safety_event)
        seen: Seen | StateUnavailableError
        try:
            seen = self.store.commit(plan.msg_id, plan.expires_at, now, plan.estop)
        except StateUnavailableError as exc:
            seen = exc
        return self.finish_commit(plan, now, seen)

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
        policy = self.policy
        try:
            plan = policy.plan(msg_id, timestamp, msg_type, safety_event, now)
            store = self.store
            policy.judge(plan, Seen(NEVER, store.watermark(), store.fence()), now)
        except ReplayAttackError as exc:
            self.refusals[exc.detail or exc.code] += 1
            raise
        return plan, now

    def finish_commit(
        self, plan: Verdict, now: float, seen: Seen | StateUnavailableError
    ) -> Verdict:
        """:meth:`commit` after the store's: judge what its atomic commit returned, or the
        error it raised."""
        try:
            return self._judge(plan, now, seen)
        except ReplayAttackError as exc:
            self.refusals[exc.detail or exc.code] += 1
            raise

    def _judge(self, plan: Verdict, now: float, seen: Seen | StateUnavailableError) -> Verdict:
        if isinstance(seen, StateUnavailableError):
            warning = estop_survives(plan.estop, plan.warning, _STATE_UNAVAILABLE)
            if warning is None:
                raise seen
            return Verdict(
                plan.msg_id, plan.timestamp, plan.window_s, plan.expires_at, warning, True
            )
        if seen.lost:
            self.losses += 1
            if self.on_loss is not None:
                self.on_loss(f"{self.store.backend} lost or replaced its state; fence raised")
        return self.policy.judge(plan, seen, now)
