"""Throughput of ReplayCache.check vs rcan 3.7.0's ReplayCache.check_and_record, same ids.

Run: ``python -m benchmarks.bench_window`` (needs the ``dev`` extra for rcan).
Both caches are pre-filled to capacity and then fed new unique ids, so every check
runs the full-cache path (ours: evict the soonest-expiring entry; rcan: evict the
oldest).  Figures are medians of several timed batches; the machine is noisy.
"""

from __future__ import annotations

import gc
import statistics
import sys
import time
import tracemalloc
from collections.abc import Callable

from antireplay import ManualClock, ReplayCache

try:
    from rcan.replay import ReplayCache as RcanCache

    HAVE_RCAN = True
except ImportError:  # pragma: no cover - benchmark-only dependency
    HAVE_RCAN = False

REPEATS = 7


def ids(prefix: str, n: int) -> list[str]:
    return [f"{prefix}-{i:012d}" for i in range(n)]


def median_ns_per_op(run_batch: Callable[[int], None], batch: int) -> float:
    """Median wall time per operation over REPEATS batches of ``batch`` operations."""
    samples = []
    for r in range(REPEATS):
        gc.collect()
        start = time.perf_counter_ns()
        run_batch(r)
        samples.append((time.perf_counter_ns() - start) / batch)
    return statistics.median(samples)


def ours_full(size: int, batch: int) -> float:
    cache = ReplayCache(window_s=300, max_size=size)  # the system clock, as rcan uses
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

    return median_ns_per_op(run, batch)


def ours_steady(size: int, batch: int) -> float:
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

    return median_ns_per_op(run, batch)


def rcan_full(size: int, batch: int) -> float:
    cache = RcanCache(window_s=300, max_size=size)
    now = time.time()
    for mid in ids("fill", size):
        cache.check_and_record(mid, now)
    fresh = ids("new", batch * REPEATS)

    def run(r: int) -> None:
        check = cache.check_and_record
        for mid in fresh[r * batch : (r + 1) * batch]:
            check(mid, now)

    return median_ns_per_op(run, batch)


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
    rows = []
    for size, batch, rcan_batch in ((10_000, 20_000, 5_000), (1_000_000, 20_000, 300)):
        ours = ours_full(size, batch)
        steady = ours_steady(size, batch)
        base = rcan_full(size, rcan_batch)
        rows.append((size, ours, steady, base))
    print(
        f"{'entries':>10} {'ours full':>12} {'ours steady':>12} {'rcan 3.7.0':>12} {'speedup':>8}"
    )
    for size, ours, steady, base in rows:
        print(f"{size:>10,} {ours:>9.0f} ns {steady:>9.0f} ns {base:>9.0f} ns {base / ours:>7.1f}x")
    small, large = rows[0][1], rows[1][1]
    print(f"our cost at 1,000,000 / at 10,000 entries: {large / small:.2f}x (target <= 1.5x)")
    print(f"speedup over rcan at 10,000 entries: {rows[0][3] / small:.1f}x (target >= 2x)")
    print(f"memory per entry (excluding the msg_id string itself): {bytes_per_entry():.0f} bytes")


if __name__ == "__main__":
    main()
