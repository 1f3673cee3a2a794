"""Stateful property test: ReplayCache against an unbounded reference model of §8.3."""

from __future__ import annotations

from dataclasses import dataclass, field

from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from antireplay import ManualClock, MessageType, ReplayAttackError, ReplayCache
from harness import fresh_cache

WINDOW, SAFETY_WINDOW, SKEW, MAX_SIZE = 30.0, 10.0, 5.0, 8
IDS = st.sampled_from([f"id{i}" for i in range(6)])
OFFSETS = st.one_of(st.integers(-45, 10).map(float), st.floats(-45, 10, allow_nan=False))
KINDS = st.sampled_from(
    [
        (MessageType.COMMAND, None),
        (MessageType.SAFETY, "ESTOP"),
        (MessageType.SAFETY, "RESUME"),
        (MessageType.STATUS, None),
    ]
)


@dataclass
class Model:
    """Unbounded memory of every accepted msg_id (and of every exact message) until expiry."""

    seen: dict[str, float] = field(default_factory=dict)
    exact: dict[tuple[str, float, int, str | None], float] = field(default_factory=dict)

    def decide(self, mid: str, ts: float, kind: tuple[int, str | None], now: float) -> str:
        msg_type, event = kind
        window = SAFETY_WINDOW if msg_type == MessageType.SAFETY else WINDOW
        if now - ts > window or ts > now + SKEW:
            return "reject"
        live = mid in self.seen and self.seen[mid] >= now
        if msg_type == MessageType.SAFETY and event == "ESTOP":
            return "accept-warn" if live else "accept"
        return "replay" if live else "accept"


class CacheVsModel(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.clock = ManualClock(wall=1_800_000_000.0)
        self.cache: ReplayCache = fresh_cache(WINDOW, MAX_SIZE, SKEW, self.clock)
        self.model = Model()
        self.stepped_back = False

    @rule(mid=IDS, offset=OFFSETS, kind=KINDS)
    def send(self, mid: str, offset: float, kind: tuple[int, str | None]) -> None:
        self.deliver(mid, self.clock.wall() + offset, kind)

    def deliver(self, mid: str, ts: float, kind: tuple[int, str | None]) -> None:
        now = self.clock.wall()
        expected = self.model.decide(mid, ts, kind, now)
        try:
            verdict = self.cache.commit(mid, ts, kind[0], kind[1])
        except ReplayAttackError as exc:
            if expected in {"accept", "accept-warn"}:
                # Only the fail-closed rules may refuse what the model accepts: the restart
                # fence (a new process) and the watermark / saturation (forgetting).
                if exc.detail == "restart_fence":
                    assert ts <= self.cache.store.status()["fence"] + SKEW
                    return
                assert exc.detail in {"watermark", "saturated"}, (expected, exc)
                assert (
                    self.cache.store.status()["evictions"] > 0
                    or self.stepped_back
                    or len(self.cache) >= MAX_SIZE
                )
            return
        assert expected != "reject", "the cache accepted a stale or future message"
        exact_key = (mid, ts, kind[0], kind[1])
        if expected == "replay":
            # Once the cache has had to forget (saturation, clock step back), a *new* message
            # reusing a forgotten msg_id with another timestamp may pass; an exact copy never.
            assert self.degraded, "the cache accepted a msg_id replay with nothing forgotten"
            assert self.model.exact.get(exact_key, -1.0) < now, "the cache accepted a replay"
        if expected == "accept-warn" and not self.degraded:
            assert verdict.warning == "REPLAY_DETECTED"
        window = SAFETY_WINDOW if kind[0] == MessageType.SAFETY else WINDOW
        self.model.seen[mid] = max(self.model.seen.get(mid, -1.0), ts + window)
        self.model.exact[exact_key] = ts + window

    @property
    def degraded(self) -> bool:
        return self.cache.store.status()["evictions"] > 0 or self.stepped_back

    @rule(data=st.data())
    def replay_exact(self, data: st.DataObject) -> None:
        """Resend an exact copy of some earlier accepted message."""
        if not self.model.exact:
            return
        keys = sorted(self.model.exact, key=repr)
        mid, ts, msg_type, event = data.draw(st.sampled_from(keys))
        self.deliver(mid, ts, (msg_type, event))

    @rule(ids=st.lists(st.text(min_size=1, max_size=4), min_size=1, max_size=20))
    def flood(self, ids: list[str]) -> None:
        for mid in ids:
            self.deliver(f"flood-{mid}", self.clock.wall(), (MessageType.COMMAND, None))

    @rule(seconds=st.floats(0, 40, allow_nan=False))
    def wait(self, seconds: float) -> None:
        self.clock.advance(seconds)

    @precondition(lambda self: not self.stepped_back)
    @rule(seconds=st.floats(0.1, 30, allow_nan=False))
    def ntp_step_back(self, seconds: float) -> None:
        self.clock.step_wall(-seconds)
        self.stepped_back = True

    @invariant()
    def bounded(self) -> None:
        assert len(self.cache) <= MAX_SIZE


SETTINGS = settings(max_examples=300, stateful_step_count=60, deadline=None)
CacheVsModel.TestCase.settings = SETTINGS
TestCacheVsModel = CacheVsModel.TestCase
