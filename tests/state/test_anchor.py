"""The state anchor: a restored copy of a SQLite store's whole directory (database, WAL and
witness together) is a detected loss when an anchor outside it (a file, a real Redis, or
both) vouches for more; exact and lazy writing; a lost anchor fails closed."""

from __future__ import annotations

import random
import shutil
import threading
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest
import redis

from antireplay import ManualClock, ReplayCache
from antireplay.core.errors import ConfigError, StateFileError, StateUnavailableError
from antireplay.state.anchor import Anchored, StateAnchor, check_anchor_path
from antireplay.state.sqlite import SqliteStore
from harness import STARTED_BEFORE_S
from harness.redis_server import RedisServer
from harness.stores import assert_fenced, sqlite_store

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

    return make  # the session's Redis: keys name a new deployment and this test's path


def session(tmp_path: Path, clock: ManualClock, anchor: StateAnchor | None) -> ReplayCache:
    store = sqlite_store(tmp_path / "state" / "state.db", clock=clock, anchor=anchor)
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
    assert cache.store.fence() <= NOW - STARTED_BEFORE_S  # its first start's, no new one
    assert isinstance(cache.store, SqliteStore) and cache.store.loss_reason is None
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
    store = cache.store
    assert isinstance(store, SqliteStore)  # not provably a loss, yet fenced, and said so
    assert "lazy state anchor's lease" in str(store.loss_reason)
    assert store.status()["data_loss_events"] == 1
    assert_fenced(cache, "X", NOW + 20.9)
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


def test_two_states_on_one_anchor_file_refuse_never_adopt(tmp_path: Path) -> None:
    """A second state (its own directory, empty or not) given the first one's anchor file
    is refused with the file, its owner and the recovery; it never adopts the deployment,
    so the first state's restore is still found behind its anchor."""
    (tmp_path / "other").mkdir()
    shared = tmp_path / "other" / "shared.anchor"
    clock = ManualClock(wall=NOW)
    a = sqlite_store(tmp_path / "a" / "state.db", clock=clock,
                    anchor=StateAnchor(tmp_path / "a" / "state.db", path=shared))  # fmt: skip
    a.commit("X", NOW + 30, NOW)
    a.close()
    with pytest.raises(StateFileError) as err:
        sqlite_store(tmp_path / "b" / "state.db", clock=clock,
                    anchor=StateAnchor(tmp_path / "b" / "state.db", path=shared))  # fmt: skip
    said = str(err.value)
    assert str(shared) in said and str(tmp_path / "a" / "state.db") in said
    assert "its own state.anchor.path" in said and "\n" not in said
    a = sqlite_store(tmp_path / "a" / "state.db", clock=clock,
                    anchor=StateAnchor(tmp_path / "a" / "state.db", path=shared))  # fmt: skip
    assert a.status()["data_loss_events"] == 0  # still A's, untouched by B
    a.close()


def test_sharers_on_other_hosts_and_mount_paths_share_one_redis_record(
    tmp_path: Path, redis_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two processes on one database, one through a symlinked mount path and another
    hostname, write one record (keyed by the deployment): a restore of the database is
    behind it, and neither host's first open counts a loss."""
    (tmp_path / "state").mkdir()
    (tmp_path / "mnt").symlink_to(tmp_path / "state")
    clock = ManualClock(wall=NOW)

    def on(host: str, where: str) -> SqliteStore:
        monkeypatch.setattr("socket.gethostname", lambda: host)
        db = tmp_path / where / "state.db"
        return sqlite_store(db, clock=clock, anchor=StateAnchor(db, redis_url=redis_url))

    a = on("host-a", "state")
    a.commit("before", NOW + 30, NOW)
    shutil.copytree(tmp_path / "state", tmp_path / "snapshot", symlinks=True)
    b = on("host-b", "mnt")
    assert b.status()["data_loss_events"] == 0  # a new hostname and path: no loss
    b.commit("X", NOW + 30, NOW)
    a.close()
    b.close()
    shutil.rmtree(tmp_path / "state")
    shutil.copytree(tmp_path / "snapshot", tmp_path / "state")
    a = on("host-a", "state")
    assert "behind its state anchor" in str(a.loss_reason)
    assert_fenced(ReplayCache(clock=clock, store=a), "X", NOW - 1)
    a.close()


def test_the_redis_anchor_never_goes_back(tmp_path: Path, redis_url: str) -> None:
    """Concurrent writers land in any order: the record keeps the highest generation and
    time (one script), so a slow writer never lowers what a fast one vouched for."""
    deployment = uuid.uuid4().hex
    fast, slow = (StateAnchor(tmp_path / "db", redis_url=redis_url) for _ in range(2))
    fast.advance(deployment, 9, NOW + 5)
    slow.advance(deployment, 4, NOW)
    assert fast.read(deployment) == {"redis://127.0.0.1:" + redis_url.rsplit(":", 1)[1]:
                                     Anchored(deployment, 9, NOW + 5)}  # fmt: skip
    fast.close()
    slow.close()
    racers = [StateAnchor(tmp_path / "db", redis_url=redis_url) for _ in range(8)]
    order = list(range(1, 41))
    random.Random(5).shuffle(order)
    threads = [
        threading.Thread(target=racers[g % 8].advance, args=(deployment, 10 + g, NOW + g))
        for g in order
    ]  # real threads, eight connections, landing in whatever order they land
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert list(racers[0].read(deployment).values()) == [Anchored(deployment, 50, NOW + 40)]
    for racer in racers:
        racer.close()


@pytest.mark.parametrize("flushed", ["redis", "file"])
def test_each_anchor_copy_is_checked_on_its_own(
    tmp_path: Path, redis_url: str, flushed: str
) -> None:
    """With a file and a Redis copy, losing either one (no restore at all) is a loss:
    the other copy does not hide it."""
    (tmp_path / "other").mkdir()
    clock = ManualClock(wall=NOW)
    db = tmp_path / "state" / "state.db"

    def anchor() -> StateAnchor:
        return StateAnchor(db, path=tmp_path / "other" / "a", redis_url=redis_url)

    store = sqlite_store(db, clock=clock, anchor=anchor())
    store.commit("X", NOW + 30, NOW)
    deployment = store._deployment
    store.close()
    if flushed == "redis":
        redis.Redis.from_url(redis_url).delete(f"antireplay:anchor:{deployment}")
    else:
        (tmp_path / "other" / "a").unlink()
    store = sqlite_store(db, clock=clock, anchor=anchor())
    assert "no state anchor" in str(store.loss_reason), store.loss_reason
    assert store.status()["data_loss_events"] == 1
    assert_fenced(ReplayCache(clock=clock, store=store), "X", NOW - 1)
    store.close()


def test_an_unreachable_anchor_opens_unready_and_verifies_once_back(tmp_path: Path) -> None:
    """Its Redis down at open: the store opens (no refusal to start), unready and refusing
    commits; once Redis answers, readiness runs the deferred loss check, which still
    finds a restored directory behind its anchor (and the next commit reports it)."""
    (tmp_path / "redis-dir").mkdir()
    server = RedisServer(tmp_path / "redis-dir", persistent=True)
    server.start()
    clock = ManualClock(wall=NOW)
    db = tmp_path / "state" / "state.db"

    def anchor() -> StateAnchor:
        return StateAnchor(db, redis_url=server.url, timeout_s=0.5)

    try:
        store = sqlite_store(db, clock=clock, anchor=anchor())
        store.commit("before", NOW + 30, NOW)
        store.close()
        shutil.copytree(tmp_path / "state", tmp_path / "snapshot")
        store = sqlite_store(db, clock=clock, anchor=anchor())
        store.commit("X", NOW + 30, NOW)
        store.close()
        shutil.rmtree(tmp_path / "state")
        shutil.copytree(tmp_path / "snapshot", tmp_path / "state")
        server.kill()
        store = sqlite_store(db, clock=clock, anchor=anchor())  # opens: no exception
        with pytest.raises(StateUnavailableError, match="state anchor"):
            store.ready()
        with pytest.raises(StateUnavailableError, match="state anchor"):
            store.commit("X", NOW + 30, NOW)
        server.start()
        store.ready()
        assert "behind its state anchor" in str(store.loss_reason)
        cache = ReplayCache(clock=clock, store=store)
        assert_fenced(cache, "X", NOW - 1)
        clock.advance(60)
        assert cache.commit("fresh", clock.wall()).warning is None
        store.close()
    finally:
        server.stop()


def test_a_running_store_is_unready_while_its_anchor_is_down(tmp_path: Path) -> None:
    (tmp_path / "redis-dir").mkdir()
    server = RedisServer(tmp_path / "redis-dir", persistent=True)
    server.start()
    db = tmp_path / "state" / "state.db"
    try:
        store = sqlite_store(db, anchor=StateAnchor(db, redis_url=server.url, timeout_s=0.5))
        store.ready()
        server.kill()
        with pytest.raises(StateUnavailableError, match="state anchor"):
            store.ready()
        server.start()
        store.ready()
        store.close()
    finally:
        server.stop()


@pytest.mark.parametrize(
    "target", ["state/state.db", "state/.state.db.witness", "state/x.anchor", "audit.db",
               "other", "/dev/null", "/proc/self/anchor", "notes.txt"],
)  # fmt: skip
def test_an_anchor_path_that_is_not_an_anchor_is_refused_untouched(
    tmp_path: Path, target: str
) -> None:
    (tmp_path / "state").mkdir()
    (tmp_path / "other").mkdir()
    (tmp_path / "notes.txt").write_text("keep me")
    db = tmp_path / "state" / "state.db"
    sqlite_store(db).close()
    (tmp_path / "audit.db").write_bytes(b"SQLite format 3\0")
    path = Path(target) if target.startswith("/") else tmp_path / target
    before = path.read_bytes() if path.is_file() and not target.startswith("/") else None
    avoid = {"state database": db, "state witness": db.with_name(".state.db.witness"),
             "audit trail": tmp_path / "audit.db"}  # fmt: skip
    with pytest.raises(ConfigError) as err:
        check_anchor_path(path, avoid)
    assert "state.anchor.path" in str(err.value) and "\n" not in str(err.value)
    if before is not None:
        assert path.read_bytes() == before
