"""Cost per commit on the path the gateway runs, per store, beside the bare store client.

Run: ``python -m benchmarks stores`` (starts its own redis-server on a free loopback port).
The gateway's path is ``ReplayCache.commit`` (window policy + the store's one atomic
commit) on the store its config names, opened by ``open_store`` as the gateway opens it:

* ``sqlite:PATH`` on disk (WAL, ``synchronous=FULL``, the witness written and synced in
  every commit), beside a **bare SQLite insert** on the same disk: WAL,
  ``synchronous=FULL``, one transaction per insert (one sync where ours has two: the
  WAL's and the witness's, which is how a lost or rolled-back file is detected);
* ``redis://`` on a real redis-server, beside a **bare redis-py** ``SET key 1 NX PX``
  on the same server (our commit is one script call: identity check, duplicate test,
  record); and ``commit_async`` with ``IN_FLIGHT`` commits awaited at once on one event
  loop, as the gateway's requests arrive: the store's group committer records each
  batch of them in one script call;
* ``memory`` (no baseline client; see ``bench_window`` for its baseline);
* the same SQLite commit with a **state anchor** (:mod:`antireplay.state.anchor`) written
  in every commit (a file: one more 64-byte ``pwrite`` + ``fdatasync``; a Redis key: one
  ``GET``-free ``SET``), and written lazily (a file, ``every_s=0.5``: at most two writes a
  second), each against the SQLite commit without one (here on the same disk; in
  production the anchor file is on another volume).

Each store holds ``LIVE`` entries before the timing.  Batches are interleaved (batch r
of every contender before batch r + 1 of any) and the figures are medians.
"""

from __future__ import annotations

import asyncio
import logging
import sqlite3
import tempfile
import time
from collections.abc import Callable
from itertools import count
from pathlib import Path

import redis

from antireplay import ManualClock, ReplayCache
from antireplay.state import open_store
from antireplay.state.anchor import StateAnchor
from antireplay.state.redis import RedisStore
from antireplay.state.sqlite import SqliteStore
from benchmarks._timing import Batch, interleaved_ns_per_op, rate
from harness.redis_server import RedisServer

LIVE = 10_000
REPEATS = 11
#: Operations per timed batch: a synced SQLite commit costs milliseconds, Redis ~0.1 ms.
BATCH = {"sqlite": 40, "redis": 1_000, "memory": 20_000}
#: Commits awaited at once in the async Redis row (the gateway benchmark's connections).
IN_FLIGHT = 32
#: The memory store's bound: room for every timed commit (``bench_window`` times a full one).
CAPACITY = LIVE + BATCH["memory"] * REPEATS + 10


class Stamps:
    """Stores and caches are built at ``t0``; the clock then moves on, past their fences.

    A new memory store fences its start time and Redis its first contact (the script
    sees no identity yet, ``verify``); messages stamped 90 s later are past both fences
    plus skew, and within the window.
    """

    def __init__(self) -> None:
        self.t0 = time.time()
        self.clock = ManualClock(wall=self.t0)
        self._next = count()

    def open(self, spec: str, anchor: StateAnchor | None = None) -> ReplayCache:
        store = open_store(spec, clock=self.clock, max_entries=CAPACITY, anchor=anchor)
        if isinstance(store, RedisStore):  # first contact (it fences), before the clock moves on
            quiet = logging.getLogger("antireplay.state.redis")
            quiet.disabled = True  # its "lost or replaced our replay state" is expected here
            store.verify()
            quiet.disabled = False
        return ReplayCache(window_s=300, max_size=CAPACITY, clock=self.clock, store=store)

    def start(self) -> None:
        self.clock.advance(100)

    def stamp(self) -> float:
        return self.t0 + 90 + next(self._next) * 1e-6


def fill(name: str, cache: ReplayCache, stamps: Stamps) -> None:
    """``LIVE`` entries, expiring after the timing (bulk-written for the durable stores)."""
    store = cache.store
    expiry = stamps.t0 + 390
    keys = [f"fill-{i}" for i in range(LIVE)]
    if name == "memory":
        for key in keys:
            cache.commit(key, stamps.stamp())
    elif isinstance(store, RedisStore):
        client = redis.Redis.from_url(store.url)
        pipe = client.pipeline(transaction=False)
        for key in keys:
            pipe.set(store.msg_key(key), repr(expiry), px=600_000)
        pipe.execute()
    elif isinstance(store, SqliteStore):  # one bulk transaction (10,000 fsyncs take minutes)
        db = sqlite3.connect(str(store.path), isolation_level=None)
        db.execute("BEGIN IMMEDIATE")
        db.executemany("INSERT INTO seen VALUES (?, ?)", [(k, expiry) for k in keys])
        db.execute("COMMIT")
        db.close()
    cache.commit(f"warm-up-{name}", stamps.stamp())


def ours(cache: ReplayCache, stamps: Stamps, prefix: str, batch: int) -> Batch:
    commit, stamp = cache.commit, stamps.stamp

    def run(r: int) -> None:
        for i in range(batch):
            commit(f"{prefix}-{r}-{i}", stamp())

    return run


def ours_async(cache: ReplayCache, stamps: Stamps, prefix: str, batch: int) -> Batch:
    """``commit_async`` with ``IN_FLIGHT`` commits in flight at once on one event loop."""
    commit, stamp = cache.commit_async, stamps.stamp

    async def flight(r: int) -> None:
        for lo in range(0, batch, IN_FLIGHT):
            ids = range(lo, min(lo + IN_FLIGHT, batch))
            await asyncio.gather(*(commit(f"{prefix}-{r}-{i}", stamp()) for i in ids))

    def run(r: int) -> None:
        asyncio.run(flight(r))

    return run


def bare_redis(url: str, batch: int) -> Batch:
    client = redis.Redis.from_url(url)
    client.set("raw-warm-up", "1", nx=True, px=300_000)  # connect outside the timing

    def run(r: int) -> None:
        set_ = client.set
        for i in range(batch):
            set_(f"raw-{r}-{i}", "1", nx=True, px=300_000)

    return run


def bare_sqlite(path: Path, batch: int) -> Batch:
    db = sqlite3.connect(str(path), isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("PRAGMA synchronous=FULL")
    db.execute("CREATE TABLE seen (key TEXT PRIMARY KEY, expires REAL NOT NULL) WITHOUT ROWID")
    execute: Callable[..., object] = db.execute

    def run(r: int) -> None:
        for i in range(batch):
            execute("BEGIN IMMEDIATE")
            execute("INSERT INTO seen VALUES (?, ?)", (f"raw-{r}-{i}", 1.0))
            execute("COMMIT")

    return run


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        server = RedisServer(Path(tmp))
        server.start()
        try:
            stamps = Stamps()
            (Path(tmp) / "anchors").mkdir()

            def anchored(
                name: str, redis_url: str | None = None, every_s: float = 0.0
            ) -> ReplayCache:
                db, file = Path(tmp) / f"{name}.db", Path(tmp) / "anchors" / name
                where = {"redis_url": redis_url} if redis_url else {"path": file}
                return stamps.open(f"sqlite:{db}", StateAnchor(db, every_s=every_s, **where))

            caches = {
                "sqlite": stamps.open(f"sqlite:{Path(tmp) / 'state.db'}"),
                "anchor-file": anchored("af"),
                "anchor-redis": anchored("ar", server.url),
                "anchor-lazy": anchored("al", every_s=0.5),
                "redis": stamps.open(server.url),
                "redis-async": stamps.open(server.url),
                "memory": stamps.open("memory"),
            }
            stamps.start()
            for name, cache in caches.items():
                fill(name, cache, stamps)
            sqlite_like = ["sqlite", "anchor-file", "anchor-redis", "anchor-lazy"]
            contenders = [
                *(
                    (ours(caches[n], stamps, n, BATCH["sqlite"]), BATCH["sqlite"])
                    for n in sqlite_like
                ),
                (bare_sqlite(Path(tmp) / "bare.db", BATCH["sqlite"]), BATCH["sqlite"]),
                (ours(caches["redis"], stamps, "rd", BATCH["redis"]), BATCH["redis"]),
                (ours_async(caches["redis-async"], stamps, "ra", BATCH["redis"]), BATCH["redis"]),
                (bare_redis(server.url, BATCH["redis"]), BATCH["redis"]),
                (ours(caches["memory"], stamps, "mm", BATCH["memory"]), BATCH["memory"]),
            ]
            measured = interleaved_ns_per_op(contenders, REPEATS)
            sq, af, ar, al, sq_bare, rd, rd_async, rd_bare, mem = measured
            for cache in caches.values():
                assert cache.refusals.total() == 0, cache.refusals
                cache.store.close()
        finally:
            server.stop()
    print(f"{LIVE:,} live entries per store; medians of {REPEATS} interleaved batches")
    rows = [
        ("sqlite: ReplayCache.commit (gateway path)", sq),
        ("sqlite + anchor file, every commit", af),
        ("sqlite + anchor Redis key, every commit", ar),
        ("sqlite + anchor file, lazy (every_s=0.5)", al),
        ("sqlite: bare insert, WAL, sync=FULL (baseline)", sq_bare),
        ("redis: ReplayCache.commit (a thread's path)", rd),
        (f"redis: ReplayCache.commit_async, {IN_FLIGHT} in flight", rd_async),
        ("redis: bare redis-py SET NX PX (baseline)", rd_bare),
        ("memory: ReplayCache.commit (gateway path)", mem),
    ]
    for name, ns in rows:
        print(f"{name:<48} {ns:>12,.0f} ns {rate(ns)}")
    print(f"sqlite: gateway path / bare insert: {sq / sq_bare:.2f}x")
    for name, ns in (("file", af), ("Redis key", ar), ("file, lazy", al)):
        print(f"sqlite: with anchor ({name}) / without: {ns / sq:.2f}x")
    print(f"redis:  one commit / bare SET NX PX: {rd / rd_bare:.2f}x")
    print(f"redis:  commit_async, {IN_FLIGHT} in flight / one commit: {rd_async / rd:.2f}x")


if __name__ == "__main__":
    main()
