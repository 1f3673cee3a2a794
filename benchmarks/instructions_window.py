"""Instructions per full-cache ``ReplayCache.commit`` (memory store), 10,000 vs 1,000,000 entries.

Run: ``python -m benchmarks.instructions_window`` (needs valgrind; takes a few minutes).
Not part of ``python -m benchmarks``: it is slow, and it answers a different question.
``bench_window`` measures time, and at 1,000,000 entries time is dominated by cache
misses of the dict (its "dict floor" row).  This counts the work itself with
``valgrind --tool=callgrind``, which is repeatable whatever else the machine does:
if a commit's work grew with the number of entries (as rcan's ``list.pop(0)``
eviction does), the count at 1,000,000 would be far above the count at 10,000.

callgrind counts only inside the compiled ``commit`` (``--toggle-collect`` on its
entry point: the window's plan and judge and the memory store's commit all run
inside it); the fill goes through ``_run``, a different entry point, so only the
saturated commits are counted, including any garbage collection they trigger.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys

from antireplay import WINDOW_BUILD

COMMITS = 20_000
#: mypyc's wrapper for ReplayCache.commit (module-prefixed: the hot modules build as one group).
ENTRY_POINT = "CPyPy_replay___ReplayCache___commit"

WORKLOAD = """
import itertools, sys, time
from antireplay import ReplayCache
from antireplay.core.messages import MessageType
size, commits = int(sys.argv[1]), int(sys.argv[2])

class StoppedClock:  # read through a C call; moved past the memory store's restart fence
    def __init__(self, at):
        self.move_to(at)
        self.monotonic = itertools.repeat(1_000.0).__next__
    def move_to(self, at):
        self.wall = itertools.repeat(at).__next__

t0 = time.time()
clock = StoppedClock(t0)
cache = ReplayCache(window_s=300, max_size=size, clock=clock)
clock.move_to(t0 + 110)
fill = cache._run  # not the counted entry point
for i in range(size):
    fill(f"fill-{i:012d}", t0 + 6 + i * (100 / size), MessageType.COMMAND, None, True)
assert len(cache) == size
fresh = [f"new-{i:012d}" for i in range(commits)]
stamps = [t0 + 107 + i * 3e-5 for i in range(commits)]  # each outlives every fill entry
commit = cache.commit
for mid, ts in zip(fresh, stamps):
    commit(mid, ts)
assert len(cache) == size and not cache.refusals, cache.refusals
"""


def per_commit(size: int) -> float:
    """Instructions per saturated commit, as callgrind counts them."""
    run = subprocess.run(
        [
            "valgrind",
            "--tool=callgrind",
            "--callgrind-out-file=/dev/null",
            "--collect-atstart=no",
            f"--toggle-collect={ENTRY_POINT}",
            sys.executable,
            "-c",
            WORKLOAD,
            str(size),
            str(COMMITS),
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    found = re.search(r"Collected : (\d+)", run.stderr)
    if found is None:
        raise SystemExit(f"callgrind printed no count:\n{run.stderr[-2000:]}")
    return int(found.group(1)) / COMMITS


def main() -> None:
    if shutil.which("valgrind") is None:
        raise SystemExit("valgrind is needed: apt-get install valgrind")
    if WINDOW_BUILD != "compiled":
        raise SystemExit("this counts the compiled build's entry point; the source build runs")
    small, large = per_commit(10_000), per_commit(1_000_000)
    print(f"{'entries':>10} {'instructions per commit':>24}")
    print(f"{10_000:>10,} {small:>24,.0f}")
    print(f"{1_000_000:>10,} {large:>24,.0f}")
    print(f"work per commit at 1,000,000 / at 10,000 entries: {large / small:.2f}x")


if __name__ == "__main__":
    main()
