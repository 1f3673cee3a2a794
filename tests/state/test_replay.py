"""ReplayCache over a store: the refusal as a value, and the msg_id index in front of the store."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from antireplay import ManualClock, ReplayCache
from antireplay.core.errors import (
    MessageStaleError,
    ReplayAttackError,
    ReplayDetectedError,
    StateUnavailableError,
)
from antireplay.core.messages import MessageType
from antireplay.core.window import Refusal, Seen
from antireplay.state.memory import MemoryStore
from antireplay.state.sqlite import SqliteStore

NOW = 2_000_000_000.0
STARTED = NOW - 400


class CountingStore(SqliteStore):
    """A SQLite store that counts its lookups (the reads ``check`` must not need)."""

    lookups = 0
    down = False

    def lookup(self, key: str) -> Seen:
        self.lookups += 1
        if self.down:
            raise StateUnavailableError("the test took the store down")
        return super().lookup(key)


@pytest.fixture
def sqlite_store(tmp_path: Path) -> Iterator[CountingStore]:
    made = CountingStore(tmp_path / "state.db", clock=ManualClock(wall=STARTED))
    yield made
    made.close()


def test_try_commit_returns_the_refusal_and_commit_raises_it() -> None:
    clock = ManualClock(wall=STARTED)
    cache = ReplayCache(clock=clock)
    clock.step_wall(NOW - STARTED)
    assert cache.try_commit("a", NOW - 1).msg_id == "a"  # type: ignore[union-attr]
    refused = cache.try_commit("a", NOW - 1)
    assert isinstance(refused, Refusal) and refused.kind is ReplayDetectedError
    assert isinstance(refused.error(), ReplayDetectedError)
    stale = cache.try_commit("old", NOW - 60)
    assert isinstance(stale, Refusal) and stale.kind is MessageStaleError
    checked = cache.try_check("a", NOW - 1)
    assert isinstance(checked, Refusal) and checked.code == "REPLAY_DETECTED"
    with pytest.raises(ReplayDetectedError):
        cache.commit("a", NOW - 1)
    assert cache.refusals["REPLAY_DETECTED"] == 3
    assert cache.refusals["MESSAGE_STALE"] == 1


def test_check_of_a_fresh_msg_id_reads_no_store(sqlite_store: CountingStore) -> None:
    cache = ReplayCache(clock=ManualClock(wall=NOW), store=sqlite_store)
    for i in range(50):
        cache.check(f"fresh-{i}", NOW - 1)
        cache.commit(f"fresh-{i}", NOW - 1)
        with pytest.raises(ReplayDetectedError):
            cache.check(f"fresh-{i}", NOW - 1)  # the index answers: this process committed it
    assert sqlite_store.lookups == 0


def test_a_replay_committed_by_another_cache_costs_one_commit_then_is_indexed(
    sqlite_store: CountingStore,
) -> None:
    clock = ManualClock(wall=NOW)
    a, b = (
        ReplayCache(clock=clock, store=sqlite_store),
        ReplayCache(clock=clock, store=sqlite_store),
    )
    a.commit("cmd", NOW - 1)
    b.check("cmd", NOW - 1)  # a miss proceeds to authentication: the commit is authoritative
    with pytest.raises(ReplayDetectedError):
        b.commit("cmd", NOW - 1)
    with pytest.raises(ReplayDetectedError):
        b.check("cmd", NOW - 1)  # now indexed: later copies never reach the crypto
    assert sqlite_store.lookups == 0


def test_an_index_that_evicted_reads_the_store_below_its_watermark(
    sqlite_store: CountingStore,
) -> None:
    clock = ManualClock(wall=NOW)
    cache = ReplayCache(clock=clock, store=sqlite_store, max_size=4)
    for i in range(8):  # each newcomer expires later: the full index evicts the soonest
        cache.commit(f"m-{i}", NOW - 10 + i)
    with pytest.raises(ReplayDetectedError):
        cache.check("m-0", NOW - 10)  # forgotten by the index, never silently: the store answers
    assert sqlite_store.lookups == 1
    cache.check("new", NOW - 1)  # expires above the index's watermark: no read
    assert sqlite_store.lookups == 1


def test_check_on_an_unreachable_store_fails_closed_except_estop(
    sqlite_store: CountingStore,
) -> None:
    clock = ManualClock(wall=NOW)
    cache = ReplayCache(clock=clock, store=sqlite_store, max_size=1)
    cache.commit("a", NOW - 10)
    cache.commit("b", NOW - 1)  # evicts "a" from the index
    sqlite_store.down = True
    refused = cache.try_check("a", NOW - 10)
    assert isinstance(refused, Refusal) and refused.kind is StateUnavailableError
    with pytest.raises(StateUnavailableError, match="took the store down"):
        cache.check("a", NOW - 10)
    estop = cache.check("a", NOW - 5, MessageType.SAFETY, "ESTOP")
    assert estop.warning == "STATE_UNAVAILABLE"


def test_the_memory_store_is_its_own_index() -> None:
    clock = ManualClock(wall=STARTED)
    store = MemoryStore(clock=clock)
    clock.step_wall(NOW - STARTED)
    a, b = ReplayCache(clock=clock, store=store), ReplayCache(clock=clock, store=store)
    a.commit("cmd", NOW - 1)
    with pytest.raises(ReplayAttackError):
        b.check("cmd", NOW - 1)  # one table: the pre-crypto check sees the other's commit
