"""Replay caches on shared stores, and what a store's restart fence looks like to a test."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Any

import pytest

from antireplay import ManualClock, MessageStaleError, ReplayCache
from antireplay.core.clock import Clock, SystemClock
from antireplay.state.redis import RedisStore
from antireplay.state.sqlite import SqliteStore
from harness import started_before


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


def sqlite_store(path: str | Path, *, clock: Clock | None = None, **kwargs: Any) -> SqliteStore:
    """A :class:`SqliteStore` on ``path``.  A state with no history (neither database nor
    witness yet) fences its first start; on a :class:`ManualClock` it is created with the
    clock stepped back (:func:`~harness.started_before`), so that fence lies long
    behind the test's "now", as a deployment started earlier (the fence has its own
    tests).  An existing state is opened as it is, loss detection and all."""
    db = Path(path)
    witness = db.with_name(f".{db.name}.witness")
    if isinstance(clock, ManualClock) and not db.exists() and not witness.exists():
        return started_before(clock, lambda: SqliteStore(db, clock=clock, **kwargs))
    return SqliteStore(db, clock=clock, **kwargs)


def aged_state(path: str | Path, clock: Clock | None = None) -> Path:
    """Create the SQLite state at ``path`` if it has no history, as a deployment first
    started ``STARTED_BEFORE_S`` before ``clock``'s now (the real clock if None): the
    gateway or store a test opens on it next proves its continuity, and its first start's
    fence lies long behind what the test sends (that fence has its own tests)."""
    db = Path(path)
    if db.exists() or db.with_name(f".{db.name}.witness").exists():
        return db  # it has a history of its own: opened as it is by whoever uses it
    now = (clock or SystemClock()).wall()
    sqlite_store(db, clock=ManualClock(wall=now)).close()
    return db
