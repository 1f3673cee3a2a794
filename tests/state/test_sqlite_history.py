"""SqliteStore: a state with no history (new, emptied, a new deployment id) fences its
first start exactly as a memory store fences every start; one whose witness and anchor
vouch for it opens unfenced."""

from __future__ import annotations

import shutil
from pathlib import Path

from antireplay import ManualClock, MessageType, ReplayCache
from antireplay.state.anchor import StateAnchor
from antireplay.state.memory import MemoryStore
from antireplay.state.sqlite import SqliteStore
from harness.stores import assert_fenced

NOW = 2_000_000_000.0


def test_a_new_state_fences_its_first_start_like_a_memory_store(tmp_path: Path) -> None:
    clock = ManualClock(wall=NOW)
    store = SqliteStore(tmp_path / "state.db", clock=clock)
    assert store.fence() == MemoryStore(clock=clock).fence() == NOW
    assert store.loss_reason is not None and store.loss_reason.startswith("no history")
    status = store.status()
    assert (status["no_history_events"], status["data_loss_events"]) == (1, 0)  # not a loss
    cache = ReplayCache(clock=clock, store=store)
    assert_fenced(cache, "x", NOW)
    assert_fenced(cache, "x", NOW + cache.policy.skew_s)  # fence + skew, as memory
    estop = cache.commit("e", NOW, MessageType.SAFETY, "ESTOP")  # a fresh ESTOP passes
    assert estop.warning is None or estop.warning == "REPLAY_DETECTED"
    clock.advance(cache.policy.skew_s + 1)
    assert cache.commit("y", clock.wall()).warning is None  # past the fence: accepted
    store.close()


def test_a_restart_with_history_raises_no_new_fence(tmp_path: Path) -> None:
    clock = ManualClock(wall=NOW)
    SqliteStore(tmp_path / "state.db", clock=clock).close()
    clock.advance(100)
    reopened = SqliteStore(tmp_path / "state.db", clock=clock)
    assert reopened.fence() == NOW and reopened.loss_reason is None  # its first start's only
    assert reopened.status()["no_history_events"] == 0
    reopened.close()


def test_an_emptied_directory_fences_again(tmp_path: Path) -> None:
    """Database, WAL and witness wiped (a redeploy, or an attacker with the disk): X,
    accepted before, is refused within its window, never accepted a second time."""
    clock, state = ManualClock(wall=NOW), tmp_path / "state"
    first = SqliteStore(state / "state.db", clock=clock)
    clock.advance(10)
    cache = ReplayCache(clock=clock, store=first)
    cache.commit("x", clock.wall())
    first.close()
    clock.advance(2)
    shutil.rmtree(state)
    second = SqliteStore(state / "state.db", clock=clock)
    assert second.loss_reason is not None and second.loss_reason.startswith("no history")
    assert_fenced(ReplayCache(clock=clock, store=second), "x", NOW + 10)
    second.close()


def test_a_brand_new_anchor_proves_nothing_about_before(tmp_path: Path) -> None:
    clock, db = ManualClock(wall=NOW), tmp_path / "state" / "state.db"
    anchor = StateAnchor(db, path=tmp_path / "anchor")
    store = SqliteStore(db, clock=clock, anchor=anchor)
    assert store.fence() == NOW and store.loss_reason is not None
    assert store.loss_reason.startswith("no history")
    store.close()
    clock.advance(100)
    exact = SqliteStore(db, clock=clock, anchor=StateAnchor(db, path=tmp_path / "anchor"))
    assert exact.fence() == NOW and exact.loss_reason is None  # it matches: nothing new
    exact.close()
