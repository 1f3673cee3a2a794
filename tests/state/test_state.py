"""One contract suite over every backend (memory, a real SQLite file, a real redis-server, a real
3-node Redis Cluster): the seen-set, the watermark and the fence, clock steps, restarts, data
loss of every kind, multi-process races and kill -9."""

from __future__ import annotations

import asyncio
import contextlib
import json
import multiprocessing
import random
import shutil
import sqlite3
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import redis
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ed25519

from antireplay import (
    ManualClock,
    MessageStaleError,
    MessageType,
    ReplayAttackError,
    ReplayCache,
    ReplayDetectedError,
)
from antireplay.core.errors import ConfigError, StateFileError, StateUnavailableError
from antireplay.mavlink import MavlinkGuard, mav_time
from antireplay.rcan.auth import sign_envelope
from antireplay.state import ReplayStore, Seen, open_store
from antireplay.state.memory import MemoryStore
from antireplay.state.redis import RedisStore
from antireplay.state.sqlite import SqliteStore
from harness import kill9_runs, run_threads
from harness.mavlink_frames import KEY, command_frame, encoder
from harness.redis_server import (
    RedisCluster,
    RedisServer,
    primary_and_replica,
    wait_replicated,
)
from harness.stores import assert_fenced as _assert_fenced
from harness.stores import fresh_deployment as _fresh_deployment
from harness.stores import redis_replicas as _replicas
from harness.stores import sqlite_store
from harness.workers import store_worker

BACKENDS = ["memory", "sqlite", "redis", "redis-cluster"]
NOW = 2_000_000_000.0  # 2033: after any Redis server's real time in these tests
#: Stores in these tests start this long before NOW, so their start-up fence is long past.
STARTED = NOW - 400


@pytest.fixture(scope="session")
def cluster_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A real 3-node Redis Cluster for this test session."""
    cluster = RedisCluster(tmp_path_factory.mktemp("cluster"))
    cluster.start()
    try:
        yield cluster.url
    finally:
        cluster.stop()


def make_store(kind: str, request: pytest.FixtureRequest, path: Path) -> ReplayStore:
    clock = ManualClock(wall=STARTED)
    if kind == "memory":
        return MemoryStore(clock=clock)
    if kind == "sqlite":
        return sqlite_store(path / "state.db", clock=clock)
    url = request.getfixturevalue("redis_url" if kind == "redis" else "cluster_url")
    made = RedisStore(url, prefix=f"t-{uuid.uuid4().hex}:", clock=clock)
    made.verify()  # a new deployment on this Redis: the first contact raises the fence
    return made


@pytest.fixture(params=BACKENDS)
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[ReplayStore]:
    made = make_store(request.param, request, tmp_path)
    yield made
    made.close()


def cache_on(store: ReplayStore, clock: ManualClock, **kwargs: float) -> ReplayCache:
    return ReplayCache(clock=clock, store=store, **kwargs)  # type: ignore[arg-type]


# --- the contract -------------------------------------------------------------------------------


def test_commit_then_lookup(store: ReplayStore) -> None:
    assert store.lookup("a").expiry == float("-inf")
    assert store.commit("a", NOW + 30, NOW).recorded
    assert store.lookup("a").expiry == NOW + 30


def test_commit_refuses_a_live_duplicate_and_returns_its_entry(store: ReplayStore) -> None:
    assert store.commit("a", NOW + 30, NOW).recorded
    again = store.commit("a", NOW + 40, NOW + 10)
    assert not again.recorded
    assert again.expiry == NOW + 30
    assert store.lookup("a").expiry == NOW + 30


def test_commit_after_expiry_succeeds(store: ReplayStore) -> None:
    assert store.commit("a", NOW + 30, NOW).recorded
    assert store.commit("a", NOW + 61, NOW + 31).recorded  # expired on our clock
    assert not store.commit("a", NOW + 62, NOW + 32).recorded


def test_forced_commit_extends_a_live_entry(store: ReplayStore) -> None:
    assert store.commit("e", NOW + 10, NOW, True).recorded
    extended = store.commit("e", NOW + 15, NOW + 5, True)
    assert (extended.recorded, extended.expiry) == (False, NOW + 10)
    assert store.lookup("e").expiry == NOW + 15


def test_threads_racing_on_commit_have_one_winner(store: ReplayStore) -> None:
    for round_no in range(20):
        wins: list[bool] = []

        def attempt(_: int, key: str = f"k{round_no}", out: list[bool] = wins) -> None:
            out.append(store.commit(key, NOW + 30, NOW).recorded)

        run_threads(6, attempt)
        assert wins.count(True) == 1


def test_advance_only_if_greater_and_64_bit_safe(store: ReplayStore) -> None:
    big = 2**64 - 2**13 - 2
    assert store.current("ctr") is None
    assert store.advance("ctr", 5)
    assert not store.advance("ctr", 5)
    assert not store.advance("ctr", 4)
    assert store.advance("ctr", big - 1)
    assert store.advance("ctr", big)
    assert not store.advance("ctr", big - 1)
    assert store.current("ctr") == big


def test_advance_race_highest_wins(store: ReplayStore) -> None:
    values = list(range(1, 41))
    random.Random(7).shuffle(values)
    threads = [threading.Thread(target=store.advance, args=("race", v)) for v in values]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert store.current("race") == 40


def test_forget_raises_the_fence_and_drops_the_counters(store: ReplayStore) -> None:
    """``forget``: the fence counter only rises, the named counters go (missing ones are
    no-ops), the fence itself is never dropped, other counters stay."""
    for key, value in (("p:a", 7), ("p:b", 9), ("p:keep", 3), ("p:floor", 5)):
        assert store.advance(key, value)
    store.forget(["p:a", "p:b", "p:missing", "p:floor"], "p:floor", 9)
    assert [store.current(k) for k in ("p:a", "p:b", "p:missing")] == [None, None, None]
    assert store.current("p:floor") == 9 and store.current("p:keep") == 3
    store.forget(["p:keep"], "p:floor", 4)  # a lower fence never lowers it
    assert store.current("p:floor") == 9 and store.current("p:keep") is None
    store.forget([], "p:new", 2)  # a fence counter that did not exist yet
    assert store.current("p:new") == 2


def test_forget_racing_advances_keeps_the_highest_fence(store: ReplayStore) -> None:
    values = list(range(1, 31))
    random.Random(3).shuffle(values)
    threads = [
        threading.Thread(target=store.forget, args=([f"f:{v}"], "f:fence", v))
        if v % 2
        else threading.Thread(target=store.advance, args=("f:fence", v))
        for v in values
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert store.current("f:fence") == 30


def test_advance_above_refuses_at_or_below_the_fence_counter(store: ReplayStore) -> None:
    """``advance_above``: a counter another process dropped under a fence (``forget``)
    cannot be advanced again from nothing to a value the fence covers."""
    assert store.advance_above("q:a", 5, "q:floor")  # no fence yet
    store.forget(["q:a"], "q:floor", 9)
    assert not store.advance_above("q:a", 9, "q:floor")
    assert store.current("q:a") is None
    assert store.advance_above("q:a", 10, "q:floor") and store.current("q:a") == 10
    assert not store.advance_above("q:a", 10, "q:floor")  # and above its own counter


def test_forget_racing_advance_above_never_reopens(store: ReplayStore) -> None:
    """Real threads: whoever wins, a value the fence covers is never recorded after the
    counter was dropped under it."""
    for round_ in range(20):
        key, fence = f"r{round_}:p", f"r{round_}:floor"
        assert store.advance(key, 5)
        racers = [
            threading.Thread(target=store.forget, args=([key], fence, 7)),
            threading.Thread(target=store.advance_above, args=(key, 6, fence)),
        ]
        for t in racers:
            t.start()
        for t in racers:
            t.join()
        assert store.current(key) is None and store.current(fence) == 7
        assert not store.advance_above(key, 7, fence)


def test_status_reports_the_backend_in_use(store: ReplayStore) -> None:
    store.commit("a", NOW + 30, NOW)
    status = store.status()
    assert set(status) >= {"entries", "watermark", "fence", "evictions", "data_loss_events"}
    assert store.backend in {"memory", "sqlite", "redis", "redis-cluster"}
    if store.backend in {"memory", "sqlite"}:
        assert status["entries"] == 1


def test_two_replicas_sharing_a_store_reject_each_others_replays(store: ReplayStore) -> None:
    clock = ManualClock(wall=NOW)
    a, b = cache_on(store, clock), cache_on(store, clock)
    a.commit("cmd-1", NOW - 1)
    with pytest.raises(ReplayDetectedError):
        b.commit("cmd-1", NOW - 1)
    with pytest.raises(ReplayDetectedError):
        b.check("cmd-1", NOW - 1)  # the pre-crypto check sees it too
    b.check("cmd-2", NOW - 1)
    a.commit("cmd-2", NOW - 1)  # check recorded nothing


def test_two_mavlink_guards_sharing_a_store_accept_a_frame_once(store: ReplayStore) -> None:
    clock = ManualClock(wall=NOW)
    guards = [MavlinkGuard(KEY, store=store, clock=clock) for _ in range(2)]
    frame = command_frame(*encoder(ts=mav_time(clock)))
    guards[0].open(frame)
    with pytest.raises(ReplayAttackError):
        guards[1].open(frame)  # its own table has never seen the stream: the store has


# --- clock steps --------------------------------------------------------------------------------


def test_clock_step_forward_and_back_never_reaccepts_an_exact_copy(store: ReplayStore) -> None:
    clock = ManualClock(wall=NOW)
    cache = cache_on(store, clock)
    captured = [(f"cmd-{i}", NOW - i) for i in range(5)]
    for mid, ts in captured:
        cache.commit(mid, ts)
    clock.step_wall(120)  # NTP steps the wall clock forward ...
    for i in range(200):  # ... traffic goes on, and every commit purges on the stepped clock
        cache.commit(f"later-{i}", clock.wall())
    clock.step_wall(-120)  # ... and back
    for mid, ts in captured:
        with pytest.raises((ReplayDetectedError, MessageStaleError)):
            cache.commit(mid, ts)
    clock.advance(0.5)
    cache.commit("fresh-after-the-step", clock.wall() + 1)  # fresh traffic still flows


def test_saturated_memory_store_fails_closed_and_evictions_raise_the_watermark() -> None:
    clock = ManualClock(wall=NOW)
    store = MemoryStore(max_entries=50, clock=ManualClock(wall=STARTED))
    cache = ReplayCache(max_size=50, clock=clock, store=store)
    cache.commit("victim", NOW - 1)
    for i in range(500):
        try:
            cache.commit(f"flood-{i}", NOW + (i % 6))
        except MessageStaleError as exc:
            assert exc.detail in {"saturated", "watermark"}
    assert cache.store.status()["entries"] <= 50
    assert cache.store.status()["evictions"] > 0
    with pytest.raises(MessageStaleError) as err:
        cache.commit("victim", NOW - 1)
    assert err.value.detail == "watermark"


def test_a_slot_left_mid_drain_keeps_its_filings() -> None:
    """A forced commit filed ahead of the slot being drained (an ESTOP expiring sooner)
    must not orphan that slot's remaining filings: every entry still leaves, by eviction
    or purge, raising the watermark."""
    store = MemoryStore(max_entries=4, restart_fence=False)
    for i in range(4):
        store.commit(f"a{i}", 100.01 + i * 0.01, 50.0)  # one slot
    store.commit("b0", 200.0, 50.0)  # evicts from that slot, which starts draining
    store.commit("estop", 60.0, 50.0, force=True)  # evicts again; filed in a sooner slot
    store.commit("b1", 200.0, 50.0)  # evicts the ESTOP's entry, the soonest
    assert store.evictions == 3
    assert store.purge(1_000.0) == 4  # the two left of the first slot, b0 and b1
    assert len(store) == 0
    assert store.watermark() == 200.0


# --- restarts -----------------------------------------------------------------------------------


def test_memory_restart_fence_refuses_every_capture_from_before_the_restart() -> None:
    clock = ManualClock(wall=NOW)
    first = ReplayCache(clock=clock)  # a store-less embed: the memory backend
    clock.advance(10)
    with pytest.raises(MessageStaleError) as err:  # within skew of the start: fenced
        first.commit("early", clock.wall() - 6)
    assert err.value.detail == "restart_fence"
    captured = clock.wall()
    first.commit("cmd", captured)
    clock.advance(3)
    restarted = ReplayCache(clock=clock)  # all memory gone
    with pytest.raises(MessageStaleError) as err:
        restarted.commit("cmd", captured)
    assert err.value.detail == "restart_fence"
    assert restarted.refusals["restart_fence"] == 1
    assert restarted.commit("estop", clock.wall(), MessageType.SAFETY, "ESTOP").warning
    clock.advance(6)
    restarted.commit("new", clock.wall())


def test_sqlite_clean_restart_keeps_everything_and_raises_no_fence(tmp_path: Path) -> None:
    clock = ManualClock(wall=NOW)
    store = sqlite_store(tmp_path / "state.db", clock=clock)
    started = store.fence()  # its first start's, long before NOW (a state with no history)
    ReplayCache(clock=clock, store=store).commit("cmd", NOW - 1)
    store.close()
    reopened = sqlite_store(tmp_path / "state.db", clock=clock)
    cache = ReplayCache(clock=clock, store=reopened)
    with pytest.raises(ReplayDetectedError):
        cache.commit("cmd", NOW - 1)
    cache.commit("fresh", NOW)
    assert reopened.fence() == started
    assert reopened.loss_reason is None


def test_redis_new_client_on_the_same_server_keeps_everything(redis_url: str) -> None:
    prefix = f"t-{uuid.uuid4().hex}:"
    clock = ManualClock(wall=NOW)
    first = RedisStore(redis_url, prefix=prefix, clock=ManualClock(wall=STARTED))
    first.verify()
    ReplayCache(clock=clock, store=first).commit("cmd", NOW - 1)
    second = RedisStore(redis_url, prefix=prefix, clock=clock)
    with pytest.raises(ReplayDetectedError):
        ReplayCache(clock=clock, store=second).commit("cmd", NOW - 1)
    assert second.data_loss_events == 0


# --- SQLite: a lost, truncated, replaced or rolled-back file ------------------------------------


def _sqlite_session(path: Path, clock: ManualClock) -> tuple[SqliteStore, ReplayCache]:
    store = sqlite_store(path, clock=clock)
    return store, ReplayCache(clock=clock, store=store)


def test_sqlite_deleted_database_is_fenced(tmp_path: Path) -> None:
    clock, db = ManualClock(wall=NOW), tmp_path / "state.db"
    store, cache = _sqlite_session(db, clock)
    cache.commit("cmd", NOW - 1)
    store.close()
    for leftover in tmp_path.glob("state.db*"):
        if not leftover.name.endswith(".witness"):
            leftover.unlink()
    store, cache = _sqlite_session(db, clock)
    assert store.loss_reason is not None and "missing" in store.loss_reason
    _assert_fenced(cache, "cmd", NOW - 1)
    assert store.status()["data_loss_events"] == 1


def test_sqlite_truncated_database_is_fenced(tmp_path: Path) -> None:
    clock, db = ManualClock(wall=NOW), tmp_path / "state.db"
    store, cache = _sqlite_session(db, clock)
    cache.commit("cmd", NOW - 1)
    store.close()
    db.write_bytes(b"")
    for wal in tmp_path.glob("state.db-*"):
        wal.unlink()
    store, cache = _sqlite_session(db, clock)
    _assert_fenced(cache, "cmd", NOW - 1)


def test_sqlite_rolled_back_database_is_fenced(tmp_path: Path) -> None:
    clock, db = ManualClock(wall=NOW), tmp_path / "state.db"
    store, cache = _sqlite_session(db, clock)
    cache.commit("early", NOW - 2)
    store.close()
    shutil.copy(db, tmp_path / "backup.db")  # an operator's backup ...
    store, cache = _sqlite_session(db, clock)
    cache.commit("cmd", NOW - 1)  # ... taken before this message was accepted
    store.close()
    shutil.copy(tmp_path / "backup.db", db)  # restored
    store, cache = _sqlite_session(db, clock)
    assert store.loss_reason is not None and "rolled back" in store.loss_reason
    _assert_fenced(cache, "cmd", NOW - 1)


def test_sqlite_forget_on_a_database_rolled_back_under_it_is_fenced(tmp_path: Path) -> None:
    """``forget`` runs the loss detection of ``advance``: a live restore under a running
    store raises the fence in the same step."""
    clock, db = ManualClock(wall=NOW), tmp_path / "state.db"
    store = sqlite_store(db, clock=clock)
    store.advance("k", 1)
    backup = sqlite3.connect(tmp_path / "backup.db")
    with sqlite3.connect(db) as source:
        source.backup(backup)
    store.advance("k", 2)
    with sqlite3.connect(db) as target:
        backup.backup(target)  # restored under the running store
    backup.close()
    fence_before = store.fence()
    store.forget(["k"], "floor", 3)
    assert store.fence() > fence_before and store.data_loss_events == 1
    assert store.current("k") is None and store.current("floor") == 3
    store.close()


def test_sqlite_database_of_another_deployment_is_fenced(tmp_path: Path) -> None:
    clock = ManualClock(wall=NOW)
    store, cache = _sqlite_session(tmp_path / "state.db", clock)
    cache.commit("cmd", NOW - 1)
    store.close()
    (tmp_path / "other").mkdir()
    other, _ = _sqlite_session(tmp_path / "other" / "state.db", clock)
    other.close()
    shutil.copy(tmp_path / "other" / "state.db", tmp_path / "state.db")
    store, cache = _sqlite_session(tmp_path / "state.db", clock)
    assert store.loss_reason is not None and "another deployment" in store.loss_reason
    _assert_fenced(cache, "cmd", NOW - 1)


def test_sqlite_lost_witness_is_fenced(tmp_path: Path) -> None:
    clock = ManualClock(wall=NOW)
    store, cache = _sqlite_session(tmp_path / "state.db", clock)
    cache.commit("cmd", NOW - 1)
    store.close()
    (tmp_path / ".state.db.witness").unlink()
    store, cache = _sqlite_session(tmp_path / "state.db", clock)
    _assert_fenced(cache, "cmd", NOW - 1)


def test_sqlite_garbage_file_is_refused_naming_the_file_and_the_recovery(tmp_path: Path) -> None:
    db = tmp_path / "state.db"
    db.write_bytes(b"this is not a database" * 200)
    with pytest.raises(StateFileError) as err:
        sqlite_store(db)
    assert str(db) in str(err.value)
    assert "mv" in err.value.recovery


def test_sqlite_fence_persists_across_a_further_restart(tmp_path: Path) -> None:
    clock, db = ManualClock(wall=NOW), tmp_path / "state.db"
    store, cache = _sqlite_session(db, clock)
    cache.commit("cmd", NOW - 1)
    store.close()
    (tmp_path / ".state.db.witness").unlink()
    _sqlite_session(db, clock)[0].close()  # fenced, then a clean stop
    store, cache = _sqlite_session(db, clock)
    assert store.loss_reason is None
    _assert_fenced(cache, "cmd", NOW - 1)


def test_sqlite_rm_glob_of_the_database_keeps_the_witness_and_is_fenced(tmp_path: Path) -> None:
    clock, db = ManualClock(wall=NOW), tmp_path / "state.db"
    store, cache = _sqlite_session(db, clock)
    cache.commit("cmd", NOW - 1)
    store.close()
    for victim in tmp_path.glob("state.db*"):  # what `rm state.db*` removes
        victim.unlink()
    store, cache = _sqlite_session(db, clock)
    _assert_fenced(cache, "cmd", NOW - 1)


def test_sqlite_loss_fence_is_no_lower_than_the_last_commit_time(tmp_path: Path) -> None:
    clock, db = ManualClock(wall=NOW), tmp_path / "state.db"
    store, cache = _sqlite_session(db, clock)
    cache.commit("cmd", NOW - 1)
    store.close()
    db.unlink()
    clock.step_wall(-20)  # the clock stepped back across the restart
    store, cache = _sqlite_session(db, clock)
    clock.advance(16)  # "cmd" is fresh again on this clock, and after fence + skew of now
    _assert_fenced(cache, "cmd", NOW - 1)


def test_sqlite_live_restore_under_a_running_store_is_fenced(tmp_path: Path) -> None:
    import sqlite3  # noqa: PLC0415 - SQLite's own backup API, as an operator would use it

    clock, db = ManualClock(wall=NOW), tmp_path / "state.db"
    store, cache = _sqlite_session(db, clock)
    cache.commit("early", NOW - 3)
    backup = sqlite3.connect(":memory:")
    sqlite3.connect(db).backup(backup)
    cache.commit("m6", NOW - 2)
    cache.commit("m7", NOW - 1)
    backup.backup(sqlite3.connect(db))  # restored in place, under the running store
    _assert_fenced(cache, "m7", NOW - 1)
    assert store.status()["data_loss_events"] == 1
    store.close()
    store, cache = _sqlite_session(db, clock)
    _assert_fenced(cache, "m6", NOW - 2)


def test_sqlite_corrupted_while_running_answers_503_and_estop_still_passes(
    tmp_path: Path,
) -> None:
    clock, db = ManualClock(wall=NOW), tmp_path / "state.db"
    store, cache = _sqlite_session(db, clock)
    for i in range(200):
        cache.commit(f"fill-{i}", NOW - 1)
    store.close()
    _, cache = _sqlite_session(db, clock)
    raw = bytearray(db.read_bytes())
    raw[100:4096] = b"\xff" * (4096 - 100)
    for page in range(1, len(raw) // 4096):
        raw[page * 4096 : page * 4096 + 64] = b"\xa5" * 64
    db.write_bytes(bytes(raw))
    with pytest.raises(StateUnavailableError) as err:
        cache.commit("cmd", NOW)
    assert str(db) in err.value.reason
    assert cache.commit("estop", NOW, MessageType.SAFETY, "ESTOP").warning == "STATE_UNAVAILABLE"


# --- Redis: restart, restore, flush, failover, eviction, clock skew -----------------------------


def test_redis_flush_is_noticed_by_every_replica(redis_url: str) -> None:
    clock = ManualClock(wall=NOW)
    a, b = _replicas(redis_url, 2, clock)
    _fresh_deployment(a, clock)
    captured = clock.wall()
    a.commit("cmd", captured)
    redis.Redis.from_url(redis_url).flushdb()
    clock.advance(1)
    _assert_fenced(b, "cmd", captured)  # the replay goes to the *other* replica
    _assert_fenced(a, "cmd", captured)  # and the fence lives in Redis, for both
    assert b.losses == 1
    assert a.losses == 0  # b noticed first; a applies the shared fence


def test_redis_restart_from_an_older_snapshot_is_fenced(tmp_path: Path) -> None:
    server = RedisServer(tmp_path, snapshots=True)
    server.start()
    try:
        clock = ManualClock(wall=NOW)
        a, b = _replicas(server.url, 2, clock)
        _fresh_deployment(a, clock)
        a.commit("old", clock.wall())
        server.save()  # the snapshot holds our meta key, but not what follows
        captured = clock.wall()
        a.commit("cmd", captured)
        server.kill()
        server.start()  # loads dump.rdb: meta is there, "cmd" is not
        clock.advance(1)
        _assert_fenced(b, "cmd", captured)
        _assert_fenced(a, "cmd", captured)
    finally:
        server.stop()


def test_redis_promoted_replica_that_missed_the_last_write_is_fenced(tmp_path: Path) -> None:
    with primary_and_replica(tmp_path) as (primary, replica, vip):
        clock = ManualClock(wall=NOW)
        a, b = _replicas(vip.url, 2, clock)
        _fresh_deployment(a, clock)
        a.commit("synced", clock.wall())
        wait_replicated(primary, replica)
        replica.client().replicaof("no", "one")  # the link breaks: the replica misses ...
        captured = clock.wall()
        a.commit("cmd", captured)  # ... this write
        primary.kill()
        vip.point_to(replica.port)  # failover: the replica is promoted behind the same address
        clock.advance(1)
        for cache in (a, b):  # a pooled connection that the failover cut answers 503 once
            assert isinstance(cache.store, RedisStore)
            with contextlib.suppress(StateUnavailableError):
                cache.store.verify()
        _assert_fenced(b, "cmd", captured)
        _assert_fenced(a, "cmd", captured)
        # the first contact with the new deployment, then the failover
        assert sum(c.store.status()["data_loss_events"] for c in (a, b)) == 2


def test_redis_cluster_flush_of_the_owning_node_is_fenced(cluster_url: str) -> None:
    clock = ManualClock(wall=NOW)
    a, b = _replicas(cluster_url, 2, clock)
    _fresh_deployment(a, clock)
    captured = clock.wall()
    a.commit("cmd", captured)
    client = redis.cluster.RedisCluster.from_url("redis://" + cluster_url.split("://", 1)[1])
    client.flushall(target_nodes=redis.cluster.RedisCluster.ALL_NODES)
    _assert_fenced(b, "cmd", captured)


def test_redis_that_may_evict_our_keys_is_refused(tmp_path: Path) -> None:
    evicting = ("--maxmemory", "64mb", "--maxmemory-policy", "allkeys-lru")
    server = RedisServer(tmp_path, extra=evicting)
    server.start()
    try:
        with pytest.raises(ConfigError, match="noeviction"):
            RedisStore(server.url)
        server.client().config_set("maxmemory-policy", "volatile-ttl")
        with pytest.raises(ConfigError, match="noeviction"):
            open_store(server.url)
    finally:
        server.stop()


def test_redis_eviction_policy_changed_at_run_time_fails_closed(tmp_path: Path) -> None:
    server = RedisServer(tmp_path)
    server.start()
    try:
        clock = ManualClock(wall=NOW)
        (cache,) = _replicas(server.url, 1, clock)
        _fresh_deployment(cache, clock)
        cache.commit("arm-1", clock.wall())
        server.client().config_set("maxmemory-policy", "volatile-ttl")
        with pytest.raises(StateUnavailableError, match="noeviction"):
            cache.commit("arm-2", clock.wall())
        with pytest.raises(StateUnavailableError, match="noeviction"):
            cache.store.advance("mav:1:1:1", 5)
    finally:
        server.stop()


def test_redis_flush_is_noticed_by_a_counter_advance(redis_url: str) -> None:
    prefix = f"t-{uuid.uuid4().hex}:"
    store = RedisStore(redis_url, prefix=prefix, clock=ManualClock(wall=STARTED))
    store.verify()
    assert store.advance("mav:1:1:1", 5)
    redis.Redis.from_url(redis_url).delete(f"{prefix}{{antireplay}}:meta")  # flushed
    store.advance("mav:1:1:1", 6)
    assert store.data_loss_events == 2  # the first contact, then the loss


def test_redis_entry_lifetime_does_not_depend_on_a_fast_replica_clock(redis_url: str) -> None:
    server_now = float(redis.Redis.from_url(redis_url).time()[0])
    fast = ManualClock(wall=server_now + 3)  # this replica's clock runs 3 s ahead
    store = RedisStore(redis_url, prefix=f"t-{uuid.uuid4().hex}:", clock=fast, skew_s=5)
    expiry = server_now + 30  # a message stamped now, on the true clock
    assert store.commit("cmd", expiry, fast.wall()).recorded
    ttl_s = redis.Redis.from_url(redis_url).pttl(store.msg_key("cmd")) / 1000
    # It lives until its expiry on the server's (true) clock, plus skew: not 3 s less.
    assert ttl_s >= expiry - server_now + 4


class SteppedClock:
    """The real clock plus an NTP-style step on the wall face (Redis TTLs run on real time)."""

    def __init__(self) -> None:
        self.step = 0.0

    def wall(self) -> float:
        return time.time() + self.step

    def monotonic(self) -> float:
        return time.monotonic()


def test_redis_replica_clock_stepping_back_never_reaccepts_a_copy_redis_dropped(
    redis_url: str,
) -> None:
    """Redis drops a key once its TTL ran out, on real time; a replica whose wall clock then
    steps back further than skew_s would see the message as fresh again.  The script's
    watermark (server time - skew_s) refuses it."""
    clock = SteppedClock()
    store = RedisStore(redis_url, prefix=f"t-{uuid.uuid4().hex}:", clock=clock, skew_s=0.5)
    fence = store.verify().fence
    cache = ReplayCache(5, 1000, 0.5, clock, safety_window_s=1, store=store)
    deadline = time.monotonic() + 10
    while clock.wall() <= fence + 0.5 and time.monotonic() < deadline:
        time.sleep(0.02)  # past the new deployment's fence (a condition, not a guess)
    ts = clock.wall()
    cache.commit("resume", ts, MessageType.SAFETY, "RESUME")  # window 1 s: TTL ~1.5 s
    clock.step = -1.0  # NTP steps this replica's wall clock back by more than skew_s
    client = redis.Redis.from_url(redis_url)
    while client.exists(store.msg_key("resume")) and time.monotonic() < deadline:
        time.sleep(0.02)  # Redis drops the key when its TTL runs out (real time)
    assert not client.exists(store.msg_key("resume"))
    assert clock.wall() - ts <= 1.0 and ts <= clock.wall() + 0.5  # fresh on the stepped clock
    with pytest.raises(MessageStaleError) as err:
        cache.commit("resume", ts, MessageType.SAFETY, "RESUME")
    assert err.value.detail == "watermark"


def test_redis_down_fails_closed_but_estop_passes_and_recovery(tmp_path: Path) -> None:
    server = RedisServer(tmp_path, persistent=True)
    server.start()
    try:
        clock = ManualClock(wall=NOW)
        (cache,) = _replicas(server.url, 1, clock)
        _fresh_deployment(cache, clock)
        cache.commit("before", clock.wall())
        server.stop()
        with pytest.raises(StateUnavailableError) as err:
            cache.commit("during", clock.wall())
        assert err.value.http_status == 503
        verdict = cache.commit("estop", clock.wall(), MessageType.SAFETY, "ESTOP")
        assert verdict.warning == "STATE_UNAVAILABLE"
        with pytest.raises(StateUnavailableError):
            cache.commit("resume", clock.wall(), MessageType.SAFETY, "RESUME")
        server.start()  # AOF kept everything, but a new server process: fenced
        clock.advance(1)
        with pytest.raises(MessageStaleError):
            cache.commit("before", clock.wall() - 1)
        clock.advance(cache.policy.skew_s + 1)
        cache.commit("after", clock.wall())
    finally:
        server.stop()


def test_commit_async_is_the_same_atomic_commit_on_every_backend(store: ReplayStore) -> None:
    """The event loop's commit: racers on one key, one winner; the entry as ``commit``'s."""

    async def race_twice() -> list[Seen]:
        return list(
            await asyncio.gather(
                store.commit_async("a", NOW + 30, NOW), store.commit_async("a", NOW + 40, NOW)
            )
        )

    assert sorted(seen.recorded for seen in asyncio.run(race_twice())) == [False, True]
    assert store.lookup("a").expiry in {NOW + 30, NOW + 40}


def test_redis_down_commit_async_fails_closed_but_estop_passes(tmp_path: Path) -> None:
    """The event loop's commit path keeps the outage rule: only a fresh ESTOP passes."""
    server = RedisServer(tmp_path)
    server.start()
    try:
        clock = ManualClock(wall=NOW)
        (cache,) = _replicas(server.url, 1, clock)
        _fresh_deployment(cache, clock)
        assert asyncio.run(cache.commit_async("before", clock.wall())).warning is None
        server.stop()
        with pytest.raises(StateUnavailableError):
            asyncio.run(cache.commit_async("during", clock.wall()))
        verdict = asyncio.run(
            cache.commit_async("estop", clock.wall(), MessageType.SAFETY, "ESTOP")
        )
        assert (verdict.warning, verdict.estop) == ("STATE_UNAVAILABLE", True)
        with pytest.raises(StateUnavailableError):
            asyncio.run(cache.commit_async("stop", clock.wall(), MessageType.SAFETY, "STOP"))
    finally:
        server.stop()


# --- processes, kill -9, bounded file -----------------------------------------------------------


def _race_processes(spec: str, rounds: int) -> list[int]:
    """Two OS processes receive the same signed messages, round by round, concurrently."""
    key = ed25519.Ed25519PrivateKey.generate()
    public = key.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    messages = [
        json.dumps(
            sign_envelope(
                {"rcan": "3.2", "msg_id": f"round-{i}", "timestamp": store_worker.WALL - 1,
                 "cmd": "move_forward", "target": "rcan://r/acme/arm/v2/u1"},
                "op", "ed25519", key,
            )
        ).encode()
        for i in range(rounds)
    ]  # fmt: skip
    ctx = multiprocessing.get_context("spawn")
    barrier, results = ctx.Barrier(2, timeout=60), ctx.Queue()
    args = (spec, messages, public, barrier, results)
    procs = [ctx.Process(target=store_worker.race_rounds, args=args) for _ in range(2)]
    for p in procs:
        p.start()
    accepted = [results.get(timeout=300), results.get(timeout=300)]
    for p in procs:
        p.join(timeout=60)
    assert all(isinstance(a, list) for a in accepted), accepted
    assert [p.exitcode for p in procs] == [0, 0]
    return sorted(accepted[0] + accepted[1])


def test_two_processes_one_sqlite_file_exactly_one_acceptance(tmp_path: Path) -> None:
    assert _race_processes(f"sqlite:{tmp_path / 'shared.db'}", 500) == list(range(500))


def test_two_processes_one_redis_exactly_one_acceptance(redis_url: str) -> None:
    db_url = redis_url.rsplit("/", 1)[0] + "/3"
    assert _race_processes(db_url, 500) == list(range(500))


def test_sqlite_kill9_under_load_never_accepts_twice(tmp_path: Path) -> None:
    runs = kill9_runs(
        ["-m", "harness.workers.store_worker", str(tmp_path / "receiver.db")], 15, 60, 5
    )
    accepted = [msg_id for run in runs for msg_id in run]
    assert accepted, "nothing was accepted"
    assert len(accepted) == len(set(accepted)), "a message was accepted twice across kill -9"


def test_sqlite_file_stays_bounded_under_sustained_load(tmp_path: Path) -> None:
    store = sqlite_store(tmp_path / "load.db")
    clock = ManualClock(wall=NOW)
    cache = ReplayCache(window_s=5, clock=clock, store=store)
    sizes = []
    for batch in range(4):
        for i in range(3_000):
            clock.advance(0.001)  # 1,000 msg/s with a 5 s window: ~5,000 live rows
            cache.commit(f"b{batch}-{i}", clock.wall())
        sizes.append((tmp_path / "load.db").stat().st_size)
    assert store.count() < 8_000
    assert sizes[-1] <= sizes[1] * 1.5, sizes


def test_open_store_specs(tmp_path: Path) -> None:
    assert isinstance(open_store("memory"), MemoryStore)
    assert isinstance(open_store(f"sqlite:{tmp_path / 'x.db'}"), SqliteStore)
    assert isinstance(open_store("redis://127.0.0.1:1/0"), RedisStore)  # down: checked later
    assert open_store("memory", max_entries=7).status()["entries"] == 0
    for bad in ("", "sqlite:", "postgres://x", "memroy"):
        with pytest.raises(ConfigError):
            open_store(bad)


class _FullDisk:
    """A connection whose next COMMIT fails the way SQLite does on a full disk."""

    def __init__(self, db: Any) -> None:
        self.db, self.failures = db, 1

    def execute(self, sql: str, *args: Any) -> Any:
        if sql == "COMMIT" and self.failures:
            self.failures -= 1
            self.db.execute("ROLLBACK")  # SQLite rolls the transaction back itself
            raise sqlite3.OperationalError("database or disk is full")
        return self.db.execute(sql, *args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.db, name)


def test_a_failed_commit_is_an_outage_not_a_rollback(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A full disk fails one batch with its own cause (503), and the next batch (or the
    next open) does not mistake the un-advanced database for a rollback."""
    clock = ManualClock(wall=NOW)
    store = sqlite_store(tmp_path / "state.db", clock=clock)
    started = store.fence()  # its first start's, long before NOW (a state with no history)
    assert store.commit("a", NOW + 30, NOW).recorded
    monkeypatch.setattr(store, "_db", _FullDisk(store._db))
    with pytest.raises(StateUnavailableError, match="disk is full"):
        store.commit("b", NOW + 30, NOW)
    monkeypatch.undo()
    seen = store.commit("b", NOW + 30, NOW)
    assert seen.recorded and not seen.lost and store.fence() == started
    assert store.data_loss_events == 0
    store.close()
    reopened = sqlite_store(tmp_path / "state.db", clock=clock)
    assert reopened.fence() == started and reopened.loss_reason is None
    reopened.close()
