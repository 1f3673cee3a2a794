"""The state anchor: a restored copy of a SQLite store's whole directory (database, WAL and
witness together) is a detected loss when an anchor outside it (a file, a real Redis, or
both) vouches for more; exact and lazy writing; a lost anchor fails closed."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import redis

from antireplay import ManualClock, ReplayCache
from antireplay.core.errors import StateUnavailableError
from antireplay.state.anchor import Anchored, StateAnchor
from antireplay.state.sqlite import SqliteStore
from tests.harness.redis_server import RedisServer
from tests.harness.stores import assert_fenced

NOW = 2_000_000_000.0
MakeAnchor = Callable[..., StateAnchor | None]


@pytest.fixture(params=["file", "redis", "both"])
def make_anchor(request: pytest.FixtureRequest, tmp_path: Path) -> MakeAnchor:
    """Anchors of the state under ``tmp_path/state`` kept in ``tmp_path/other`` (another
    volume in production), in a real Redis, or both."""
    (tmp_path / "other").mkdir()
    url = None if request.param == "file" else request.getfixturevalue("redis_url")
    path = None if request.param == "redis" else tmp_path / "other" / "state.anchor"

    def make(every_s: float = 0.0) -> StateAnchor:
        return StateAnchor(
            tmp_path / "state" / "state.db", path=path, redis_url=url, every_s=every_s
        )

    if url is not None:  # the session's Redis: start this test's database path afresh
        redis.Redis.from_url(url).delete(make().key)
    return make


def session(tmp_path: Path, clock: ManualClock, anchor: StateAnchor | None) -> ReplayCache:
    store = SqliteStore(tmp_path / "state" / "state.db", clock=clock, anchor=anchor)
    return ReplayCache(clock=clock, store=store)


def restarted(
    tmp_path: Path, clock: ManualClock, make_anchor: MakeAnchor, between: Callable[[], object]
) -> ReplayCache:
    """Accept X, stop, do ``between`` to the state directory, start again."""
    cache = session(tmp_path, clock, make_anchor())
    cache.commit("X", NOW - 1)
    cache.store.close()
    between()
    return session(tmp_path, clock, make_anchor())


def accept_then_restore(
    tmp_path: Path, clock: ManualClock, make_anchor: MakeAnchor, every_s: float = 0.0
) -> ReplayCache:
    """Accept one command, copy the whole state directory, accept X, restore the copy."""
    cache = session(tmp_path, clock, make_anchor(every_s))
    cache.commit("before", NOW - 2)
    cache.store.close()
    shutil.copytree(tmp_path / "state", tmp_path / "snapshot")
    cache = session(tmp_path, clock, make_anchor(every_s))
    clock.advance(0.5)
    cache.commit("X", NOW - 1)
    cache.store.close()
    shutil.rmtree(tmp_path / "state")
    shutil.copytree(tmp_path / "snapshot", tmp_path / "state")
    clock.advance(0.5)
    return session(tmp_path, clock, make_anchor(every_s))


def test_a_restored_directory_behind_its_anchor_is_a_loss(
    tmp_path: Path, make_anchor: MakeAnchor
) -> None:
    clock = ManualClock(wall=NOW)
    cache = accept_then_restore(tmp_path, clock, make_anchor)
    store = cache.store
    assert isinstance(store, SqliteStore)
    assert store.loss_reason is not None and "behind its state anchor" in store.loss_reason
    assert store.status()["data_loss_events"] == 1
    assert_fenced(cache, "X", NOW - 1)
    store.close()


def test_without_an_anchor_the_restored_directory_accepts_x_again(tmp_path: Path) -> None:
    """The limitation the anchor removes (documented; ``serve`` and ``config check`` warn)."""
    clock = ManualClock(wall=NOW)
    cache = accept_then_restore(tmp_path, clock, lambda every_s: None)
    assert cache.store.status()["data_loss_events"] == 0
    assert cache.commit("X", NOW - 1).warning is None
    cache.store.close()


def test_a_clean_restart_on_an_exact_anchor_raises_no_fence(
    tmp_path: Path, make_anchor: MakeAnchor
) -> None:
    clock = ManualClock(wall=NOW)
    cache = restarted(tmp_path, clock, make_anchor, lambda: None)
    assert cache.store.status()["data_loss_events"] == 0
    assert cache.store.fence() == float("-inf")
    assert cache.commit("b", NOW - 0.5).warning is None
    cache.store.close()


def test_state_deleted_with_its_witness_is_a_loss_when_anchored(
    tmp_path: Path, make_anchor: MakeAnchor
) -> None:
    """Without an anchor, ``rm -r`` of the directory looks like a new deployment."""
    clock = ManualClock(wall=NOW)
    cache = restarted(tmp_path, clock, make_anchor, lambda: shutil.rmtree(tmp_path / "state"))
    assert "database and witness missing" in str(getattr(cache.store, "loss_reason", ""))
    assert_fenced(cache, "X", NOW - 1)
    cache.store.close()


def test_a_lost_or_unreadable_anchor_fails_closed(tmp_path: Path) -> None:
    """Existing state with no anchor (lost, or the first use of one) and a damaged anchor
    are losses: nothing can vouch for the directory any more."""
    (tmp_path / "other").mkdir()
    clock = ManualClock(wall=NOW)
    anchor_file = tmp_path / "other" / "state.anchor"

    def anchor() -> StateAnchor:
        return StateAnchor(tmp_path / "state" / "state.db", path=anchor_file)

    cache = session(tmp_path, clock, None)
    cache.commit("X", NOW - 1)
    cache.store.close()
    cache = session(tmp_path, clock, anchor())  # first use on existing state
    assert "no state anchor" in str(getattr(cache.store, "loss_reason", ""))
    assert_fenced(cache, "X", NOW - 1)
    cache.store.close()
    anchor_file.write_bytes(b"\0" * 64)
    cache = session(tmp_path, clock, anchor())
    assert "unreadable" in str(getattr(cache.store, "loss_reason", ""))
    assert cache.store.status()["data_loss_events"] == 2
    cache.store.close()


def test_a_lazy_anchor_writes_at_most_once_per_interval(
    tmp_path: Path, make_anchor: MakeAnchor
) -> None:
    clock = ManualClock(wall=NOW)
    anchor = make_anchor(every_s=0.5)
    assert anchor is not None
    cache = session(tmp_path, clock, anchor)
    for i in range(200):  # 200 commits over 2 s
        clock.advance(0.01)
        cache.commit(f"m{i}", clock.wall() - 0.1)
    assert 2 <= anchor.writes <= 1 + 2 / 0.5 + 1, anchor.writes
    cache.store.close()


def test_a_lazy_anchor_fences_a_copy_it_cannot_tell_from_the_latest(
    tmp_path: Path, make_anchor: MakeAnchor
) -> None:
    """The copy is taken after the anchor's last write and X is committed inside its lease
    (no write): the restored copy is as new as the anchor, not provably a loss, yet the
    restart fence at the lease's end refuses X; past the lease, fresh commands pass."""
    clock = ManualClock(wall=NOW)
    anchor = make_anchor(every_s=5.0)
    assert anchor is not None
    cache = session(tmp_path, clock, anchor)  # its open writes the anchor: lease to NOW + 10
    clock.advance(20)
    cache.commit("before", clock.wall() - 0.1)  # the lease ran out: written, to NOW + 30
    shutil.copytree(tmp_path / "state", tmp_path / "snapshot")  # idle: crash-consistent
    clock.advance(1)
    cache.commit("X", clock.wall() - 0.1)
    assert anchor.writes == 2  # X rode on the lease
    cache.store.close()
    shutil.rmtree(tmp_path / "state")
    shutil.copytree(tmp_path / "snapshot", tmp_path / "state")
    clock.advance(1)
    cache = session(tmp_path, clock, make_anchor(every_s=5.0))
    assert cache.store.status()["data_loss_events"] == 0  # not provably a loss ...
    assert_fenced(cache, "X", NOW + 20.9)  # ... yet X stays refused
    assert cache.store.fence() == NOW + 30
    clock.advance(18)
    assert cache.commit("fresh", clock.wall() - 0.1).warning is None
    cache.store.close()


def test_a_failed_anchor_write_fails_the_commit_and_recovers(tmp_path: Path) -> None:
    """The anchor is written before COMMIT: with its Redis down the commit is refused
    (STATE_UNAVAILABLE, nothing recorded); once it is back, the commit goes through and a
    restart finds no loss."""
    server = RedisServer(tmp_path / "redis-dir", persistent=True)
    (tmp_path / "redis-dir").mkdir()
    server.start()
    clock = ManualClock(wall=NOW)

    def anchor() -> StateAnchor:
        return StateAnchor(tmp_path / "state" / "state.db", redis_url=server.url, timeout_s=0.5)

    try:
        cache = session(tmp_path, clock, anchor())
        server.kill()
        with pytest.raises(StateUnavailableError, match="state anchor"):
            cache.store.commit("X", NOW + 30, NOW)
        assert cache.store.lookup("X").expiry == float("-inf")
        server.start()
        assert cache.store.commit("X", NOW + 30, NOW).recorded
        cache.store.close()
        cache = session(tmp_path, clock, anchor())
        assert cache.store.status()["data_loss_events"] == 0
        cache.store.close()
    finally:
        server.stop()


def test_the_anchor_reads_the_most_advanced_of_file_and_redis(
    tmp_path: Path, redis_url: str
) -> None:
    """Losing one of the two copies loses nothing: the other still vouches."""
    (tmp_path / "other").mkdir()
    both = StateAnchor(
        tmp_path / "db", path=tmp_path / "other" / "a", redis_url=redis_url, every_s=0.0
    )
    both.advance("ab" * 16, 7, NOW)
    (tmp_path / "other" / "a").unlink()
    assert both.read() == Anchored("ab" * 16, 7, NOW)
    redis.Redis.from_url(redis_url).set(both.key, "not an anchor")
    assert both.read() is False
    both.close()
