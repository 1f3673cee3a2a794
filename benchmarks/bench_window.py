"""Throughput of ReplayCache.check vs rcan 3.7.0's ReplayCache.check_and_record, same ids.

Run: ``python -m benchmarks.bench_window`` (needs the ``dev`` extra for rcan).
Both caches are pre-filled to capacity and then fed new unique ids, so every check
runs the full-cache path (ours: evict the soonest-expiring entry; rcan: evict the
oldest).  Figures are medians of several timed batches; the machine is noisy.

Both builds of our window run side by side: the installed one (the mypyc extension
in a normal install) and the pure-Python source.  The "dict floor" row times the
three bare dict operations every full-cache check needs (look up the new id, insert
it, delete the evicted one) at the same sizes: at 1,000,000 entries these miss the
CPU caches, and that growth is the hardware's, common to any dict-based cache.
"""

from __future__ import annotations

import gc
import statistics
import sys
import time
import tracemalloc
from collections.abc import Callable

from antireplay import WINDOW_BUILD, ManualClock, ReplayCache, _native

try:
    from rcan.replay import ReplayCache as RcanCache

    HAVE_RCAN = True
except ImportError:  # pragma: no cover - benchmark-only dependency
    HAVE_RCAN = False

REPEATS = 7
SOURCE_BUILD: type[ReplayCache] = _native.load_source("antireplay._window_source").ReplayCache


Batch = Callable[[int], None]  # runs batch number r of one contender


def ids(prefix: str, n: int) -> list[str]:
    return [f"{prefix}-{i:012d}" for i in range(n)]


def interleaved_ns_per_op(contenders: list[tuple[Batch, int]]) -> list[float]:
    """Median ns per operation of each ``(run_batch, batch size)``, batches interleaved.

    Batch r of every contender runs before batch r + 1 of any, so a burst of noise on
    this shared machine lands on all of them alike instead of skewing one ratio.
    """
    samples: list[list[float]] = [[] for _ in contenders]
    for r in range(REPEATS):
        for (run_batch, batch), out in zip(contenders, samples, strict=True):
            gc.collect()
            start = time.perf_counter_ns()
            run_batch(r)
            out.append((time.perf_counter_ns() - start) / batch)
    return [statistics.median(out) for out in samples]


def ours_full(impl: type[ReplayCache], size: int, batch: int) -> Batch:
    cache = impl(window_s=300, max_size=size)  # the system clock, as rcan uses
    now = time.time()
    for i, mid in enumerate(ids("fill", size)):
        cache.check(mid, now - 200 + i * (100 / size))
    fresh = ids("new", batch * REPEATS)
    stamps = [now - 99 + i * 1e-4 for i in range(len(fresh))]  # each expires after the last

    def run(r: int) -> None:
        check = cache.check
        lo, hi = r * batch, (r + 1) * batch
        for mid, ts in zip(fresh[lo:hi], stamps[lo:hi], strict=True):
            check(mid, ts)

    return run


def ours_steady(size: int, batch: int) -> Batch:
    """Live set of ``size`` entries kept by expiry (clock advances), no saturation."""
    clock = ManualClock(wall=time.time())
    cache = ReplayCache(window_s=30, max_size=size * 2, clock=clock)
    step = 30 / size
    for mid in ids("fill", size):
        clock.advance(step)
        cache.check(mid, clock.wall())
    fresh = ids("new", batch * REPEATS)

    def run(r: int) -> None:
        check, advance, wall = cache.check, clock.advance, clock.wall
        for mid in fresh[r * batch : (r + 1) * batch]:
            advance(step)
            check(mid, wall())

    return run


def dict_floor(size: int, batch: int) -> Batch:
    """Bare dict get (miss) + insert + delete per operation on a table of ``size`` ids."""
    table = dict.fromkeys(ids("fill", size), 0.0)
    victims = ids("fill", size)
    fresh = ids("new", batch * REPEATS)
    victims.extend(fresh)

    def run(r: int) -> None:
        get = table.get
        lo = r * batch
        for i, mid in enumerate(fresh[lo : lo + batch], lo):
            get(mid)
            table[mid] = 1.0
            del table[victims[i]]

    return run


def rcan_full(size: int, batch: int) -> Batch:
    cache = RcanCache(window_s=300, max_size=size)
    now = time.time()
    for mid in ids("fill", size):
        cache.check_and_record(mid, now)
    fresh = ids("new", batch * REPEATS)

    def run(r: int) -> None:
        check = cache.check_and_record
        for mid in fresh[r * batch : (r + 1) * batch]:
            check(mid, now)

    return run


def bytes_per_entry(n: int = 100_000) -> float:
    clock = ManualClock(wall=time.time())
    gc.collect()
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    cache = ReplayCache(window_s=300, max_size=n, clock=clock)
    for mid in ids("m", n):
        cache.check(mid, clock.wall())
    after = tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    id_bytes = sum(sys.getsizeof(m) for m in ids("m", n))
    return (after - before - id_bytes) / n


def main() -> None:
    if not HAVE_RCAN:
        raise SystemExit("rcan==3.7.0 is needed for the baseline: pip install -e '.[dev]'")
    print(f"installed window build: {WINDOW_BUILD}")
    rows = []
    for size, batch, rcan_batch in ((10_000, 20_000, 5_000), (1_000_000, 20_000, 300)):
        contenders = [
            (ours_full(ReplayCache, size, batch), batch),
            (ours_full(SOURCE_BUILD, size, batch), batch),
            (ours_steady(size, batch), batch),
            (rcan_full(size, rcan_batch), rcan_batch),
            (dict_floor(size, batch), batch),
        ]
        ours, source, steady, base, floor = interleaved_ns_per_op(contenders)
        rows.append((size, ours, source, steady, base, floor))
        del contenders
    print(
        f"{'entries':>10} {'installed':>12} {'source':>12} {'steady':>12} {'rcan 3.7.0':>12}"
        f" {'speedup':>8} {'dict floor':>12}"
    )
    for size, ours, source, steady, base, floor in rows:
        print(
            f"{size:>10,} {ours:>9.0f} ns {source:>9.0f} ns {steady:>9.0f} ns {base:>9.0f} ns"
            f" {base / ours:>7.1f}x {floor:>9.0f} ns"
        )
    (_, small, small_src, _, base, small_floor), (_, large, _, _, _, large_floor) = rows
    print(f"speedup over rcan at 10,000 entries: {base / small:.1f}x (target >= 2x)")
    print(f"  (source build: {base / small_src:.1f}x)")
    print(f"our cost at 1,000,000 / at 10,000 entries: {large / small:.2f}x (target <= 1.5x)")
    print(
        f"  growth {large - small:.0f} ns per check, of which the bare dict's own growth"
        f" {large_floor - small_floor:.0f} ns"
    )
    print(f"memory per entry (excluding the msg_id string itself): {bytes_per_entry():.0f} bytes")


if __name__ == "__main__":
    main()
