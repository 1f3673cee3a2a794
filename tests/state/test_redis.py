"""The Redis store: what it tells an operator when it notices a loss, and the losses only
Redis can cause (eviction under a policy put back, a REPLICAOF round trip, a server clock
step forward), each staged on real redis-server processes and replayed to two replicas."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import uuid
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import pytest
import redis
import yaml

from antireplay import ManualClock, MessageStaleError, ReplayCache
from antireplay.audit import tail
from antireplay.cli.demo import write_demo_config
from antireplay.core.errors import StateFileError, StateUnavailableError
from antireplay.core.window import Seen
from antireplay.state.redis import RedisStore
from harness import accepted_fresh, data_losses, post_after_cut, reencoded, serving
from harness.redis_server import RedisCluster, RedisServer, wait_replicated
from harness.stores import assert_fenced, fresh_deployment, redis_replicas

NOW = 2_000_000_000.0  # 2033: after any Redis server's real time in these tests


def test_redis_fence_log_line_prints_a_number(
    redis_url: str, caplog: pytest.LogCaptureFixture
) -> None:
    """The loss warning shows the fence as seconds, not Redis's raw reply bytes."""
    clock = ManualClock(wall=NOW)
    (cache,) = redis_replicas(redis_url, 1, clock)
    fresh_deployment(cache, clock)
    captured = clock.wall()
    cache.commit("cmd", captured)
    redis.Redis.from_url(redis_url).flushdb()
    clock.advance(1)
    with caplog.at_level(logging.WARNING, logger="antireplay"):
        assert_fenced(cache, "cmd", captured)
    lines = [r.getMessage() for r in caplog.records if "fence raised to" in r.getMessage()]
    assert lines, caplog.text
    shown = lines[0].rsplit("fence raised to ", 1)[1]
    assert "b'" not in shown
    assert float(shown) > NOW


def _poisoned(url: str, key: str | None, field: str, value: str) -> RedisStore:
    """A store on a fresh prefix whose meta hash (``key`` None) or entry ``key`` holds
    ``value`` (a hand edit, another program, a torn write)."""
    prefix = f"poison{uuid.uuid4().hex}:"
    store = RedisStore(url, prefix=prefix, clock=ManualClock(wall=NOW))
    store.verify()
    raw = redis.Redis.from_url(url)
    if key is None:
        raw.hset(f"{prefix}{{antireplay}}:meta", field, value)
    else:
        raw.set(store.msg_key(key), value)
    raw.close()
    return store


@pytest.mark.parametrize(
    ("field", "value"), [("fence", "abc"), ("wm", "abc"), ("losses", "abc"), ("fence", "nan")]
)
def test_an_undecodable_meta_field_is_a_state_file_error_naming_the_key(
    redis_url: str, field: str, value: str
) -> None:
    """At start (``verify``) it refuses the start; on a commit or a readiness probe it is
    503; each names the URL, the field and the recovery (drop the meta: the next
    operation fences)."""
    store = _poisoned(redis_url, None, field, value)
    with pytest.raises(StateFileError) as refused:
        store.verify()
    assert refused.value.path == redis_url and f"meta {field}" in refused.value.problem
    assert "DEL" in refused.value.recovery and "meta" in refused.value.recovery
    for op in (partial(store.commit, "cmd", NOW + 60, NOW), store.ready):
        with pytest.raises(StateUnavailableError) as err:
            op()
        assert redis_url in err.value.reason and f"meta {field}" in err.value.reason
    store.close()


def test_an_undecodable_entry_is_503_naming_the_key(redis_url: str) -> None:
    store = _poisoned(redis_url, "cmd", "", "abc")
    for op in (partial(store.lookup, "cmd"), partial(store.commit, "cmd", NOW + 60, NOW)):
        with pytest.raises(StateUnavailableError) as err:
            op()
        assert redis_url in err.value.reason and store.msg_key("cmd") in err.value.reason
    store.close()


@pytest.fixture
def server(tmp_path: Path) -> Iterator[RedisServer]:
    """A redis-server of this test's own (its configuration, role and clock get changed)."""
    started = RedisServer(tmp_path, stepped_clock=True)
    started.start()
    yield started
    started.stop()


@pytest.fixture
def other(tmp_path: Path) -> Iterator[RedisServer]:
    """A second redis-server: another master to replicate from, or a replica."""
    (tmp_path / "other").mkdir()
    started = RedisServer(tmp_path / "other")
    started.start()
    yield started
    started.stop()


def _evict_every_entry(raw: redis.Redis) -> None:
    """``volatile-ttl`` and a low ``maxmemory``; fill (keys without TTL, in our hash slot)
    until the server has evicted every key with a TTL (our entries, and only them); then
    ``noeviction`` and no limit again, as if nothing had happened."""
    used = int(raw.info("memory")["used_memory"])
    raw.config_set("maxmemory-policy", "volatile-ttl")
    raw.config_set("maxmemory", str(used + 256 * 1024))
    for i in range(10_000):
        if raw.info("keyspace")["db0"].get("expires", 0) == 0:
            break
        with contextlib.suppress(redis.OutOfMemoryError):  # nothing more it may evict
            raw.set(f"{{antireplay}}filler:{i}", "x" * 4096)
    assert raw.info("keyspace")["db0"].get("expires", 0) == 0
    raw.config_set("maxmemory", "0")
    raw.config_set("maxmemory-policy", "noeviction")
    raw.close()


def _losses(*caches: ReplayCache) -> int:
    return sum(int(c.store.status()["data_loss_events"]) for c in caches)


def test_an_eviction_under_a_policy_put_back_is_fenced_on_every_replica(
    server: RedisServer,
) -> None:
    """Our entries are the only keys with a TTL: ``volatile-ttl`` and a low ``maxmemory``
    evict them first; with ``noeviction`` and no limit put back, the policy check passes,
    ``meta`` survived, and only the server's eviction count tells."""
    clock = ManualClock(wall=NOW)
    a, b = redis_replicas(server.url, 2, clock)
    fresh_deployment(a, clock)
    captured = clock.wall()
    a.commit("cmd", captured)
    assert isinstance(a.store, RedisStore)
    _evict_every_entry(server.client())
    raw = server.client()
    assert not raw.exists(a.store.msg_key("cmd")) and raw.exists(f"{a.store.msg_key('')[:-2]}meta")
    clock.advance(1)
    assert_fenced(b, "cmd", captured)  # the other replica, first
    assert_fenced(a, "cmd", captured)  # and the one that accepted it
    assert _losses(a, b) == 2  # the first contact, then the eviction
    assert b.store.status()["data_loss_events"] == 1
    assert "evicted" in str(getattr(b.store, "loss_reason", ""))


def test_an_eviction_on_the_cluster_node_owning_our_slot_is_fenced(cluster_url: str) -> None:
    """In a cluster the script runs on the node that owns our slot, and reads that node's
    own eviction count."""
    clock = ManualClock(wall=NOW)
    a, b = redis_replicas(cluster_url, 2, clock)
    fresh_deployment(a, clock)
    captured = clock.wall()
    a.commit("cmd", captured)
    assert isinstance(a.store, RedisStore)
    cluster = redis.cluster.RedisCluster.from_url(cluster_url.replace("+cluster", ""))
    owner = cluster.get_node_from_key(a.store.msg_key("cmd"))  # type: ignore[no-untyped-call]
    cluster.close()
    _evict_every_entry(redis.Redis(host=owner.host, port=owner.port))
    clock.advance(1)
    assert_fenced(b, "cmd", captured)
    assert_fenced(a, "cmd", captured)
    assert _losses(a, b) == 2


def test_a_replicaof_round_trip_is_fenced_on_every_replica(
    server: RedisServer, other: RedisServer
) -> None:
    """The server copies another master's older data set (REPLICAOF there) and is made a
    master again: the same process (``run_id``), a new replication history."""
    clock = ManualClock(wall=NOW)
    a, b = redis_replicas(server.url, 2, clock)
    fresh_deployment(a, clock)
    a.commit("synced", clock.wall())
    other.client().replicaof("127.0.0.1", server.port)
    wait_replicated(server, other)  # the other holds our meta, and "synced"
    other.client().replicaof("no", "one")
    fresh_deployment(a, clock)  # a first replica renewed the history: fenced, and past it
    captured = clock.wall()
    a.commit("cmd", captured)  # the other never sees this
    run_id = server.client().info("server")["run_id"]
    server.client().replicaof("127.0.0.1", other.port)  # takes the other's data set ...
    wait_replicated(other, server)
    server.client().replicaof("no", "one")  # ... and is a master again
    assert server.client().info("server")["run_id"] == run_id
    clock.advance(1)
    assert_fenced(b, "cmd", captured)
    assert_fenced(a, "cmd", captured)
    assert _losses(a, b) == 3  # the first contact, the first replica, the round trip


def test_a_first_replica_attaching_fences_once(server: RedisServer, other: RedisServer) -> None:
    """A master's first replica makes it start a new replication history: the same data,
    but the same sign as a round trip through another master's, so it fences once (as a
    restart that lost nothing does), and only once."""
    clock = ManualClock(wall=NOW)
    a, b = redis_replicas(server.url, 2, clock)
    fresh_deployment(a, clock)
    a.commit("before", clock.wall())
    replid = server.client().info("replication")["master_replid"]
    other.client().replicaof("127.0.0.1", server.port)
    wait_replicated(server, other)
    assert server.client().info("replication")["master_replid"] != replid
    assert b.store.verify().lost
    assert not a.store.verify().lost
    assert _losses(a, b) == 2  # the first contact, then the new history


def test_a_server_clock_step_forward_never_reopens_what_expired_early(
    server: RedisServer,
) -> None:
    """The server's wall clock jumps an hour ahead: Redis expires our entry early.  The next
    operation (any replica) sees the server ahead of its own clock beyond skew and keeps the
    watermark in Redis, counted as a loss: once the clock is stepped back, the copy of the
    command is still refused, by every replica."""
    seconds, micros = server.client().time()
    clock = ManualClock(wall=seconds + micros / 1e6)  # the real time, like the server's
    a, b = redis_replicas(server.url, 2, clock)
    fresh_deployment(a, clock)
    clock.advance(1)  # past the fence (the server's time at the first contact) plus skew
    captured = clock.wall()
    a.commit("cmd", captured)
    assert isinstance(a.store, RedisStore)
    server.step_clock(3600)
    assert not server.client().exists(a.store.msg_key("cmd"))  # expired, an hour early
    with pytest.raises(MessageStaleError):  # fail closed while the server runs ahead
        b.commit("other", clock.wall())
    server.step_clock(0)
    clock.advance(1)
    for replica in (b, a):
        with pytest.raises(MessageStaleError) as err:
            replica.commit("cmd", captured)
        assert err.value.detail == "watermark"
    assert _losses(a, b) == 2  # the first contact, then the clock step
    assert "clock" in str(getattr(b.store, "loss_reason", ""))


def test_a_command_replayed_to_another_gateway_process_after_an_eviction_is_refused(
    server: RedisServer, tmp_path: Path
) -> None:
    """Two ``antireplay serve`` processes on one Redis: A accepts a command; Redis evicts
    it under a policy put back since; the copy sent to B is 408 restart_fence, the loss
    counted and audited, and A refuses it too."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    config_a = write_demo_config(tmp_path / "a", store=server.url)
    config = yaml.safe_load(config_a.read_text())
    config["audit"] = str(tmp_path / "b" / "audit.db")
    config_b = tmp_path / "b" / "antireplay.yaml"
    config_b.write_text(yaml.safe_dump(config))
    with serving(config_a) as gateway_a, serving(config_b) as gateway_b:
        captured = accepted_fresh(gateway_a, tmp_path / "a")
        _evict_every_entry(server.client())
        losses = data_losses(gateway_b)
        replay = post_after_cut(gateway_b, reencoded(captured))
        assert (replay.status_code, replay.json().get("detail")) == (408, "restart_fence")
        again = post_after_cut(gateway_a, reencoded(captured))  # its own memo may answer first
        assert again.status_code in {408, 409}, again.text
        assert data_losses(gateway_b) == losses + 1
    records = tail(tmp_path / "b" / "audit.db", 1000)
    assert any(r.code == "STATE_LOST" for r in records), records


@pytest.fixture(scope="module")
def cluster_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    cluster = RedisCluster(tmp_path_factory.mktemp("cluster"))
    cluster.start()
    yield cluster.url
    cluster.stop()


@pytest.mark.parametrize("kind", ["redis", "redis-cluster"])
def test_forget_drops_counters_and_raises_the_fence_in_one_script(
    request: pytest.FixtureRequest, kind: str
) -> None:
    """``forget`` deletes the counters (missing ones are no-ops), never lowers the fence
    counter, and runs the loss checks of ``advance`` (a flushed meta is a loss)."""
    url = request.getfixturevalue("redis_url" if kind == "redis" else "cluster_url")
    prefix = f"t-{uuid.uuid4().hex}:"
    store = RedisStore(url, prefix=prefix, clock=ManualClock(wall=NOW))
    store.verify()
    assert store.advance("p:a", 5) and store.advance("p:b", 7) and store.advance("fence", 3)
    store.forget(["p:a", "p:b", "p:missing", "fence"], "fence", 10)
    assert (store.current("p:a"), store.current("p:b"), store.current("fence")) == (None, None, 10)
    store.forget([], "fence", 4)
    assert store.current("fence") == 10
    raw = (
        redis.Redis.from_url(url)
        if kind == "redis"
        else redis.cluster.RedisCluster.from_url(url.replace("redis+cluster://", "redis://"))
    )
    raw.delete(f"{prefix}{{antireplay}}:meta")  # flushed
    store.forget(["p:c"], "fence", 11)
    assert store.current("fence") == 11
    assert store.data_loss_events == 2  # the first contact, then the flush
    store.close()


def test_batched_commits_from_two_stores_accept_each_msg_id_exactly_once(redis_url: str) -> None:
    """Two store objects (two replicas) race async commits of the same msg_ids: each batch is
    one script call, and across batches and stores exactly one commit records each id."""
    prefix = f"race{uuid.uuid4().hex}:"
    clock = ManualClock(wall=NOW)
    stores = [RedisStore(redis_url, prefix=prefix, clock=clock) for _ in range(2)]
    stores[0].verify()
    ids = [f"cmd-{i}" for i in range(200)]

    async def race() -> list[Seen]:
        attempts = [s.commit_async(m, NOW + 30, NOW) for m in ids for s in stores for _ in "ab"]
        return await asyncio.gather(*attempts)

    try:
        seen = asyncio.run(race())
        recorded = [0] * len(ids)
        for n, result in enumerate(seen):
            recorded[n // 4] += result.recorded
            assert result.recorded or result.expiry == NOW + 30
        assert recorded == [1] * len(ids)
        batches = sum(s.group_commit.batches for s in stores)
        assert batches < len(seen) / 2  # batched: far fewer script calls than commits
    finally:
        for s in stores:
            s.close()


def test_a_loss_found_by_a_batch_is_flagged_once(redis_url: str) -> None:
    """The loss checks run once per script call: one batch after a FLUSHDB reports the loss
    on its first record only (one audit row, one data-loss event), fencing every record."""
    prefix = f"batchloss{uuid.uuid4().hex}:"
    clock = ManualClock(wall=NOW)
    store = RedisStore(redis_url, prefix=prefix, clock=clock)
    store.verify()  # a new deployment: the first contact fences (one event)
    before = store.data_loss_events
    redis.Redis.from_url(redis_url).delete(f"{prefix}{{antireplay}}:meta")
    try:
        ops = [(f"m-{i}", NOW + 30, NOW, False) for i in range(5)]
        results = store._commit_batch(ops)
        assert [isinstance(r, Seen) and r.lost for r in results] == [True] + [False] * 4
        assert all(isinstance(r, Seen) and r.fence >= NOW for r in results)
        assert store.data_loss_events == before + 1
    finally:
        store.close()
