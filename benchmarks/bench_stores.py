"""Checks per second for each store backend at 10,000 and 1,000,000 live entries.

Run: ``python -m benchmarks.bench_stores`` (starts its own redis-server on a free port).
Baseline for Redis: a bare redis-py ``SET key value NX PX ttl`` loop (and a bare pipeline
for batches) on the same server, measured side by side; our overhead must stay < 1.5x.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import redis
from tests.redis_server import RedisServer

from antireplay import ManualClock, ReplayCache
from antireplay.stores.memory import MemoryStore
from antireplay.stores.redis_store import RedisStore
from antireplay.stores.sqlite import SqliteStore
from benchmarks._timing import per_op_ns, rate

NOW = 1_800_000_000.0
BATCH = 100


def fill(store: MemoryStore | SqliteStore | RedisStore, n: int) -> None:
    items = [(f"fill-{i}", NOW + 200) for i in range(n)]
    for start in range(0, n, 10_000):
        store.record_many(items[start : start + 10_000], NOW)


def measure(
    name: str, store: MemoryStore | SqliteStore | RedisStore, ops: int
) -> list[tuple[str, float]]:
    clock = ManualClock(wall=NOW + 100)
    cache = ReplayCache(window_s=300, clock=clock, store=store)
    single = iter(range(10**9))
    rows = [
        (
            f"{name}: ReplayCache.check",
            per_op_ns(lambda: cache.check(f"s-{next(single)}", NOW + 99), ops, 5),
        )
    ]
    batches = iter(range(10**9))

    def batch() -> None:
        b = next(batches)
        store.record_many([(f"b-{b}-{i}", NOW + 300) for i in range(BATCH)], NOW + 100)

    rows.append(
        (
            f"{name}: record_many x{BATCH} (per msg)",
            per_op_ns(batch, max(1, ops // BATCH), 5) / BATCH,
        )
    )
    return rows


def redis_baseline(url: str, ops: int) -> list[tuple[str, float]]:
    client = redis.Redis.from_url(url)
    keys = iter(range(10**9))
    single = per_op_ns(lambda: client.set(f"raw-{next(keys)}", "1", nx=True, px=300_000), ops, 5)
    batches = iter(range(10**9))

    def batch() -> None:
        b = next(batches)
        pipe = client.pipeline(transaction=False)
        for i in range(BATCH):
            pipe.set(f"rawb-{b}-{i}", "1", nx=True, px=300_000)
        pipe.execute()

    return [
        ("redis-py bare SET NX PX (baseline)", single),
        (
            f"redis-py bare pipeline x{BATCH} (per msg)",
            per_op_ns(batch, max(1, ops // BATCH), 5) / BATCH,
        ),
    ]


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        server = RedisServer(Path(tmp))
        server.start()
        try:
            for live in (10_000, 1_000_000):
                print(f"\n-- {live:,} live entries --")
                started = time.perf_counter()
                stores: dict[str, MemoryStore | SqliteStore | RedisStore] = {
                    "memory": MemoryStore(clock=ManualClock(wall=NOW - 60), max_entries=2_000_000),
                    "sqlite": SqliteStore(Path(tmp) / f"bench-{live}.db"),
                    "redis": RedisStore(
                        server.url, prefix=f"b{live}:", clock=ManualClock(wall=NOW - 60)
                    ),
                }
                for store in stores.values():
                    fill(store, live)
                print(f"(filled in {time.perf_counter() - started:.1f}s)")
                rows = measure("memory", stores["memory"], 20_000)
                rows += measure("sqlite", stores["sqlite"], 300)
                redis_rows = measure("redis", stores["redis"], 3_000)
                base = redis_baseline(server.url, 3_000)
                for name, ns in rows + redis_rows + base:
                    print(f"{name:<44} {ns:>10,.0f} ns {rate(ns)}")
                print(
                    f"redis overhead, single: {redis_rows[0][1] / base[0][1]:.2f}x (target < 1.5x)"
                )
                print(
                    f"redis overhead, batch:  {redis_rows[1][1] / base[1][1]:.2f}x (target < 1.5x)"
                )
                redis.Redis.from_url(server.url).flushall()
        finally:
            server.stop()


if __name__ == "__main__":
    main()
