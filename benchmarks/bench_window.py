"""Cost per full-cache commit: the memory backend beside rcan, the dict floor and the old
compiled window's recorded figure.

Run: ``python -m benchmarks window`` (needs the ``dev`` extra for rcan).
Contenders, at 10,000 and 1,000,000 entries, every one pre-filled to capacity and fed
new unique ids, so each call runs the full-cache path (evict the soonest-expiring entry;
rcan evicts the oldest):

* **memory backend**: ``ReplayCache.commit`` on its default :class:`MemoryStore`, the
  installed build (the mypyc extensions in a normal install): the path an embedder runs.
* **old compiled window**, a recorded figure (:data:`OLD_WINDOW`): the window as it was
  before the replay store split out, compiled with mypyc, timed on this workload beside
  rcan and the dict floor; its code is not kept in the tree.  The ratio against it is
  printed raw and scaled by the dict floor of both runs (the machine's speed then and now).
* **rcan 3.7.0** ``check_and_record``.
* **dict floor**: the three bare dict operations every full-cache call needs (look up
  the new id, insert it, delete the evicted one); at 1,000,000 entries these miss the
  CPU caches, and that growth is the hardware's, common to any dict-based cache.
* **refusals** (10,000 entries): a duplicate of an id in the full table, through
  ``ReplayCache.try_commit`` (a ``Refusal`` value returned, as rcan returns one) and
  ``ReplayCache.commit`` (which raises ``ReplayDetectedError``, caught here), beside
  rcan's ``check_and_record`` (a ``(False, reason)`` value; its ``logger.warning`` is
  silenced, as our refusal logs nothing either).

``--quick`` runs the 10,000-entry rows only.

Batches are interleaved (batch r of every contender before batch r + 1 of any) and the
figures are medians, so noise on this shared machine lands on all contenders alike.
Our contenders read a stopped clock through a C call, as the system clock reads
``time.time``: the clock is not what is measured.
"""

from __future__ import annotations

import gc
import itertools
import logging
import statistics
import sys
import time
import tracemalloc
from collections.abc import Callable
from typing import NamedTuple

from antireplay import WINDOW_BUILD, ReplayCache
from antireplay.core.errors import ReplayAttackError
from antireplay.core.window import Refusal
from benchmarks._timing import Batch, interleaved_ns_per_op

try:
    from rcan.replay import ReplayCache as RcanCache

    HAVE_RCAN = True
except ImportError:  # pragma: no cover - benchmark-only dependency
    HAVE_RCAN = False

REPEATS = 7
GOAL_EVERY_ROUND = 3.0


class Recorded(NamedTuple):
    """ns per full-cache operation at (10,000, 1,000,000) entries, and where they were taken."""

    old_window: tuple[float, float]
    rcan: tuple[float, float]
    dict_floor: tuple[float, float]
    where: str


#: The old compiled window (mypyc, before the replay store split out: its ``check``
#: recording), measured by this benchmark's workload, the same run's medians.
OLD_WINDOW = Recorded(
    old_window=(845, 1232), rcan=(2387, 167769), dict_floor=(191, 696),
    where="2026-12-06, 2-core AMD EPYC runner shared with other jobs, CPython 3.11.7",
)  # fmt: skip


class StoppedClock:
    """A clock that stands still at ``at`` until moved, read through a C call."""

    def __init__(self, at: float) -> None:
        self.wall: Callable[[], float] = itertools.repeat(at).__next__
        self.monotonic: Callable[[], float] = itertools.repeat(1_000.0).__next__

    def move_to(self, at: float) -> None:
        self.wall = itertools.repeat(at).__next__


def ids(prefix: str, n: int) -> list[str]:
    return [f"{prefix}-{i:012d}" for i in range(n)]


class Workload:
    """The same stamps for our contenders: a full table, then newcomers that outlive it.

    The memory store's restart fence refuses anything stamped at or before its start
    plus skew, so the caches are built at ``t0`` and the clock then moves to ``t0 + 110``.
    """

    def __init__(self, size: int, batch: int) -> None:
        self.t0 = time.time()
        self.now = self.t0 + 110
        self.fill = ids("fill", size)
        self.fill_stamps = [self.t0 + 6 + i * (100 / size) for i in range(size)]
        self.fresh = ids("new", batch * REPEATS)
        # Later than every fill stamp, within the skew of now; each expires last.  About
        # 3,300 per 0.1 s slot of the memory store: a newcomer always outlives the soonest
        # slot, so it evicts (a table filling one slot would refuse it, fail-closed).
        self.stamps = [self.t0 + 107 + i * 3e-5 for i in range(len(self.fresh))]
        self.batch = batch

    def runner(self, call: Callable[[str, float], object]) -> Batch:
        fresh, stamps, batch = self.fresh, self.stamps, self.batch

        def run(r: int) -> None:
            lo, hi = r * batch, (r + 1) * batch
            for mid, ts in zip(fresh[lo:hi], stamps[lo:hi], strict=True):
                call(mid, ts)

        return run


def memory_full(work: Workload, size: int) -> Batch:
    clock = StoppedClock(work.t0)
    cache = ReplayCache(window_s=300, max_size=size, clock=clock)
    clock.move_to(work.now)
    commit = cache.commit
    for mid, ts in zip(work.fill, work.fill_stamps, strict=True):
        commit(mid, ts)
    assert len(cache) == size
    return work.runner(commit)


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


def memory_refusals(work: Workload, size: int, batch: int, *, raising: bool) -> Batch:
    """``commit`` (``raising``) or ``try_commit`` of ids the full table already holds:
    every call is a refusal."""
    clock = StoppedClock(work.t0)
    cache = ReplayCache(window_s=300, max_size=size, clock=clock)
    clock.move_to(work.now)
    for mid, ts in zip(work.fill, work.fill_stamps, strict=True):
        cache.commit(mid, ts)
    dupes = [(work.fill[i % size], work.fill_stamps[i % size]) for i in range(batch)]

    def run_raising(_: int) -> None:
        commit = cache.commit
        for mid, ts in dupes:
            try:
                commit(mid, ts)
            except ReplayAttackError:
                continue
            raise AssertionError("a replay was accepted")

    def run(_: int) -> None:
        try_commit = cache.try_commit
        for mid, ts in dupes:
            if not isinstance(try_commit(mid, ts), Refusal):
                raise AssertionError("a replay was accepted")

    return run_raising if raising else run


def rcan_refusals(size: int, batch: int) -> Batch:
    """rcan's ``check_and_record`` of ids it holds (its warning log silenced)."""
    logging.getLogger("rcan.replay").setLevel(logging.ERROR)
    cache = RcanCache(window_s=300, max_size=size)
    now = time.time()
    fill = ids("fill", size)
    for mid in fill:
        cache.check_and_record(mid, now)
    dupes = [fill[i % size] for i in range(batch)]

    def run(_: int) -> None:
        check = cache.check_and_record
        for mid in dupes:
            if check(mid, now)[0]:
                raise AssertionError("a replay was accepted")

    return run


class Rounds(NamedTuple):
    """One contender's batches: wall and thread-CPU ns per operation, and the garbage
    collections that ran inside each timed batch."""

    wall_ns: list[float]
    cpu_ns: list[float]
    collections: list[int]


def per_round(contenders: list[tuple[Batch, int]], repeats: int) -> list[Rounds]:
    """:func:`~benchmarks._timing.interleaved_ns_per_op`, keeping every round: the goal
    holds in every round, not just the median.  Thread CPU time beside the wall time: on
    a shared box a round's wall time also holds what other processes took."""
    out = [Rounds([], [], []) for _ in contenders]
    runs = [0]

    def count(phase: str, _info: dict[str, int]) -> None:
        if phase == "start":
            runs[0] += 1

    gc.callbacks.append(count)
    try:
        for r in range(repeats):
            for (run_batch, batch), rounds in zip(contenders, out, strict=True):
                gc.collect()
                runs[0] = 0
                start, cpu = time.perf_counter_ns(), time.thread_time_ns()
                run_batch(r)
                rounds.cpu_ns.append((time.thread_time_ns() - cpu) / batch)
                rounds.wall_ns.append((time.perf_counter_ns() - start) / batch)
                rounds.collections.append(runs[0])
    finally:
        gc.callbacks.remove(count)
    return out


def print_rounds(rounds: list[Rounds]) -> None:
    """Each round's ratio against rcan (wall, CPU) and the collections inside it; the
    goal (>= 3x) is judged on the worst round."""
    ours, rcan = rounds
    wall = [b / a for a, b in zip(ours.wall_ns, rcan.wall_ns, strict=True)]
    cpu = [b / a for a, b in zip(ours.cpu_ns, rcan.cpu_ns, strict=True)]
    print("rounds at 10,000 entries, rcan / ours (wall; thread CPU):")
    for r, (w, c) in enumerate(zip(wall, cpu, strict=True)):
        print(
            f"  round {r}: ours {ours.wall_ns[r]:>6.0f} ns ({ours.cpu_ns[r]:>5.0f} CPU),"
            f" rcan {rcan.wall_ns[r]:>6.0f} ns ({rcan.cpu_ns[r]:>5.0f} CPU): {w:.2f}x; {c:.2f}x"
            f"   collections in the batch: ours {ours.collections[r]}, rcan {rcan.collections[r]}"
        )
    worst = min(wall)
    print(
        f"worst round vs rcan at 10,000 entries: {worst:.2f}x wall, {min(cpu):.2f}x CPU"
        f" (goal >= {GOAL_EVERY_ROUND:g}x in every round): "
        f"{'PASS' if worst >= GOAL_EVERY_ROUND else 'MISS'}"
    )


def bytes_per_entry(n: int = 100_000) -> float:
    """Memory the memory backend holds per entry, excluding the msg_id string itself."""
    t0 = time.time()
    clock = StoppedClock(t0)
    gc.collect()
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    cache = ReplayCache(window_s=300, max_size=n, clock=clock)
    clock.move_to(t0 + 10)
    for mid in ids("m", n):
        cache.commit(mid, t0 + 10)
    after = tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    id_bytes = sum(sys.getsizeof(m) for m in ids("m", n))
    return (after - before - id_bytes) / n


def main(argv: list[str] | None = None) -> None:
    if not HAVE_RCAN:
        raise SystemExit("rcan==3.7.0 is needed for the baseline: pip install -e '.[dev]'")
    print(f"memory backend build: {WINDOW_BUILD}")
    print(
        f"old compiled window recorded {OLD_WINDOW.where}: {OLD_WINDOW.old_window} ns"
        f" beside rcan {OLD_WINDOW.rcan} ns and the dict floor {OLD_WINDOW.dict_floor} ns"
    )
    quick = "--quick" in (sys.argv[1:] if argv is None else argv)
    rows: list[tuple[int, float, float, float]] = []
    sizes = ((10_000, 20_000, 5_000), (1_000_000, 20_000, 300))
    for size, batch, rcan_batch in sizes[:1] if quick else sizes:
        work = Workload(size, batch)
        contenders = [
            (memory_full(work, size), batch),
            (rcan_full(size, rcan_batch), rcan_batch),
            (dict_floor(size, batch), batch),
        ]
        if size == 10_000:
            rounds = per_round(contenders[:2], REPEATS)
            ours, base = (statistics.median(r.wall_ns) for r in rounds)
            (floor,) = interleaved_ns_per_op(contenders[2:], REPEATS)
        else:
            ours, base, floor = interleaved_ns_per_op(contenders, REPEATS)
        rows.append((size, ours, base, floor))
        if size == 10_000:
            refused, raised, rcan_refused = interleaved_ns_per_op(
                [
                    (memory_refusals(work, size, batch, raising=False), batch),
                    (memory_refusals(work, size, batch, raising=True), batch),
                    (rcan_refusals(size, batch), batch),
                ],
                REPEATS,
            )
        del contenders, work
    print(
        f"{'entries':>10} {'memory commit':>14} {'rcan 3.7.0':>12} {'vs rcan':>8}"
        f" {'dict floor':>12} {'old window (recorded)':>22} {'ratio':>7} {'scaled':>7}"
    )
    for index, (size, ours, base, floor) in enumerate(rows):
        old, old_floor = OLD_WINDOW.old_window[index], OLD_WINDOW.dict_floor[index]
        scaled = (ours / floor) / (old / old_floor)
        print(
            f"{size:>10,} {ours:>11.0f} ns {base:>9.0f} ns {base / ours:>7.1f}x"
            f" {floor:>9.0f} ns {old:>19.0f} ns {ours / old:>6.2f}x {scaled:>6.2f}x"
        )
        print(
            f"memory backend / old compiled window (recorded) at {size:,} entries:"
            f" {ours / old:.2f}x raw, {scaled:.2f}x scaled by the dict floor (goal <= 1.5x)"
        )
    _, small, base, small_floor = rows[0]
    print(f"speedup over rcan at 10,000 entries: {base / small:.1f}x (goal >= 3x)")
    print_rounds(rounds)
    print(
        f"refusals at 10,000 entries: try_commit {refused:.0f} ns ({rcan_refused / refused:.2f}x"
        f" rcan, goal >= 1x), commit raising {raised:.0f} ns ({rcan_refused / raised:.2f}x),"
        f" rcan {rcan_refused:.0f} ns"
    )
    if quick:
        return
    _, large, _, large_floor = rows[1]
    print(
        f"our cost at 1,000,000 / at 10,000 entries: {large / small:.2f}x"
        f" (the bare dict's own growth: {large_floor - small_floor:.0f} ns of"
        f" {large - small:.0f} ns)"
    )
    print(f"memory per entry (excluding the msg_id string itself): {bytes_per_entry():.0f} bytes")


if __name__ == "__main__":
    main()
