"""Replay caches on shared stores, and what a store's restart fence looks like to a test."""

from __future__ import annotations

import uuid

import pytest

from antireplay import ManualClock, MessageStaleError, ReplayCache
from antireplay.state.redis import RedisStore


def assert_fenced(cache: ReplayCache, mid: str, ts: float) -> None:
    """Committing ``mid`` stamped ``ts`` is refused by the restart fence."""
    with pytest.raises(MessageStaleError) as err:
        cache.commit(mid, ts)
    assert err.value.detail == "restart_fence"


def redis_replicas(url: str, n: int, clock: ManualClock) -> list[ReplayCache]:
    """``n`` caches sharing one fresh key prefix on the Redis at ``url``."""
    prefix = f"t-{uuid.uuid4().hex}:"
    caches = []
    for _ in range(n):
        store = RedisStore(url, prefix=prefix, clock=clock, timeout_s=0.5)
        caches.append(ReplayCache(clock=clock, store=store))
    return caches


def fresh_deployment(cache: ReplayCache, clock: ManualClock) -> None:
    """The first contact with a new Redis fences (a new deployment looks like a flush)."""
    assert isinstance(cache.store, RedisStore)
    cache.store.verify()
    clock.advance(cache.policy.skew_s + 1)
