"""One contract suite over every backend (real SQLite file, real redis-server), plus
multi-process races, kill -9 restarts, the restart fence and Redis outages."""

from __future__ import annotations

import json
import multiprocessing
import random
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ed25519

from antireplay import (
    ManualClock,
    MessageStaleError,
    MessageType,
    ReplayCache,
    ReplayDetectedError,
)
from antireplay.auth import sign_envelope
from antireplay.errors import ConfigError, StateUnavailableError
from antireplay.stores import ReplayStore, open_store
from antireplay.stores.memory import MemoryStore
from antireplay.stores.redis_store import RedisStore
from antireplay.stores.sqlite import SqliteStore
from tests.conftest import kill9_runs, run_threads
from tests.helpers import store_worker
from tests.redis_server import RedisServer

BACKENDS = ["memory", "sqlite", "redis"]
NOW = 1_800_000_000.0


@pytest.fixture(params=BACKENDS)
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[ReplayStore]:
    if request.param == "memory":
        made: ReplayStore = MemoryStore(clock=ManualClock(wall=NOW - 60))
    elif request.param == "sqlite":
        made = SqliteStore(tmp_path / "state.db")
    else:
        url = request.getfixturevalue("redis_url")
        made = RedisStore(url, prefix=f"t-{uuid.uuid4().hex}:", clock=ManualClock(wall=NOW - 60))
    yield made
    made.close()


# --- the contract -------------------------------------------------------------------------------


def test_record_then_lookup(store: ReplayStore) -> None:
    assert store.lookup("a") is None
    assert store.record("a", NOW + 30, NOW)
    assert store.lookup("a") == NOW + 30


def test_record_refuses_unexpired_duplicate(store: ReplayStore) -> None:
    assert store.record("a", NOW + 30, NOW)
    assert not store.record("a", NOW + 40, NOW + 10)
    assert store.lookup("a") == NOW + 30


def test_record_after_expiry_succeeds(store: ReplayStore) -> None:
    assert store.record("a", NOW + 30, NOW)
    assert store.record("a", NOW + 61, NOW + 31)  # expired on our clock, whatever Redis thinks
    assert not store.record("a", NOW + 62, NOW + 32)


def test_record_many_batch(store: ReplayStore) -> None:
    assert store.record("b", NOW + 30, NOW)
    assert store.record_many([("a", NOW + 30), ("b", NOW + 30), ("c", NOW + 30)], NOW) == [
        True,
        False,
        True,
    ]


def test_threads_racing_on_record_have_one_winner(store: ReplayStore) -> None:
    for round_no in range(30):
        wins: list[bool] = []

        def attempt(_: int, key: str = f"k{round_no}", out: list[bool] = wins) -> None:
            out.append(store.record(key, NOW + 30, NOW))

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


def test_fence_semantics(store: ReplayStore) -> None:
    store.lookup("warm-up")  # a RedisStore checks its sentinel on first use
    if isinstance(store, SqliteStore):
        assert store.fence() == float("-inf")
    else:  # a fresh memory store, or a Redis without our sentinel, may have forgotten
        assert store.fence() == NOW - 60


def test_two_replicas_sharing_a_store_reject_each_others_replays(store: ReplayStore) -> None:
    clock = ManualClock(wall=NOW)
    store.lookup("warm-up")
    a = ReplayCache(clock=clock, store=store)
    b = ReplayCache(clock=clock, store=store)
    a.check("cmd-1", NOW - 1)
    with pytest.raises(ReplayDetectedError):
        b.check("cmd-1", NOW - 1)
    b.precheck("cmd-2", NOW - 1)
    a.check("cmd-2", NOW - 1)  # precheck recorded nothing


def test_open_store_specs(tmp_path: Path) -> None:
    assert isinstance(open_store("memory"), MemoryStore)
    assert isinstance(open_store(f"sqlite:{tmp_path / 'x.db'}"), SqliteStore)
    assert isinstance(open_store("redis://127.0.0.1:1/0"), RedisStore)
    for bad in ("", "sqlite:", "postgres://x", "memroy"):
        with pytest.raises(ConfigError):
            open_store(bad)


# --- restart fence ------------------------------------------------------------------------------


def test_memory_store_restart_fence_rejects_pre_restart_capture() -> None:
    clock = ManualClock(wall=NOW)
    first = ReplayCache(clock=clock, store=MemoryStore(clock=clock))
    clock.advance(10)
    captured_ts = clock.wall()
    with pytest.raises(MessageStaleError) as err:  # within skew of the start: fenced
        first.check("early", clock.wall() - 6)
    assert err.value.detail == "restart_fence"
    first.check("cmd", captured_ts)
    clock.advance(3)
    restarted = ReplayCache(clock=clock, store=MemoryStore(clock=clock))  # all memory gone
    with pytest.raises(MessageStaleError) as err:
        restarted.check("cmd", captured_ts)
    assert err.value.detail == "restart_fence"
    assert restarted.fence_rejections == 1
    assert restarted.check("estop", clock.wall(), MessageType.SAFETY, "ESTOP").warning
    clock.advance(6)
    restarted.check("new", clock.wall())


def test_memory_store_full_fails_closed() -> None:
    store = MemoryStore(max_entries=3)
    for i in range(3):
        store.record(f"k{i}", NOW + 30, NOW)
    with pytest.raises(StateUnavailableError):
        store.record("k3", NOW + 30, NOW)


# --- SQLite: processes, kill -9, bounded file --------------------------------------------------


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
    assert _race_processes(f"sqlite:{tmp_path / 'shared.db'}", 1_000) == list(range(1_000))


def test_two_processes_one_redis_exactly_one_acceptance(redis_url: str) -> None:
    db_url = redis_url.rsplit("/", 1)[0] + "/3"
    assert _race_processes(db_url, 1_000) == list(range(1_000))


def test_sqlite_kill9_under_load_never_accepts_twice(tmp_path: Path) -> None:
    runs = kill9_runs(
        ["-m", "tests.helpers.store_worker", str(tmp_path / "receiver.db")], 15, 60, 5
    )
    accepted = [msg_id for run in runs for msg_id in run]
    assert accepted, "nothing was accepted"
    assert len(accepted) == len(set(accepted)), "a message was accepted twice across kill -9"


def test_sqlite_file_stays_bounded_under_sustained_load(tmp_path: Path) -> None:
    store = SqliteStore(tmp_path / "load.db")
    clock = ManualClock(wall=NOW)
    cache = ReplayCache(window_s=5, clock=clock, store=store)
    sizes = []
    for batch in range(6):
        for i in range(4_000):
            clock.advance(0.001)  # 1,000 msg/s with a 5 s window: ~5,000 live rows
            cache.check(f"b{batch}-{i}", clock.wall())
        sizes.append((tmp_path / "load.db").stat().st_size)
    assert store.count() < 8_000
    assert sizes[-1] <= sizes[1] * 1.5, sizes


# --- Redis outage -------------------------------------------------------------------------------


def test_redis_down_fails_closed_but_estop_passes_and_recovery(tmp_path: Path) -> None:
    server = RedisServer(tmp_path, persistent=True)
    server.start()
    try:
        clock = ManualClock(wall=NOW)
        store = RedisStore(server.url, clock=ManualClock(wall=NOW - 60), timeout_s=0.2)
        cache = ReplayCache(clock=clock, store=store)
        cache.check("before", NOW - 1)
        server.stop()
        with pytest.raises(StateUnavailableError) as err:
            cache.check("during", NOW - 1)
        assert err.value.http_status == 503
        verdict = cache.check("estop", NOW - 1, MessageType.SAFETY, "ESTOP")
        assert verdict.warning == "STATE_UNAVAILABLE"
        with pytest.raises(StateUnavailableError):
            cache.check("resume", NOW - 1, MessageType.SAFETY, "RESUME")
        server.start()  # AOF kept our state and our sentinel
        with pytest.raises(ReplayDetectedError):
            cache.check("before", NOW - 1)
        cache.check("after", NOW - 1)
        assert store.data_loss_events == 1  # only the first-ever start
    finally:
        server.stop()


def test_redis_that_lost_its_data_is_fenced(tmp_path: Path) -> None:
    server = RedisServer(tmp_path, persistent=False)
    server.start()
    try:
        clock = ManualClock(wall=NOW)
        store = RedisStore(server.url, clock=clock, timeout_s=0.2)
        store.lookup("warm-up")
        clock.advance(6)
        cache = ReplayCache(clock=clock, store=store)
        captured = clock.wall()
        cache.check("cmd", captured)
        server.stop()
        with pytest.raises(StateUnavailableError):
            cache.check("x", clock.wall())
        server.start()  # came back empty: the replay must still fail
        with pytest.raises(MessageStaleError) as err:
            cache.check("cmd", captured)
        assert err.value.detail == "restart_fence"
        assert store.data_loss_events == 2
    finally:
        server.stop()
