"""Instructions per full-cache ``ReplayCache.check`` at 10,000 and 1,000,000 entries.

Run: ``python -m benchmarks.instructions_window`` (needs valgrind; takes a few minutes).
Not part of ``python -m benchmarks``: it is slow, and it answers a different question.
``bench_window`` measures time, and at 1,000,000 entries time is dominated by cache
misses of the dict (its "dict floor" row).  This counts the work itself with
``valgrind --tool=callgrind``, which is repeatable whatever else the machine does:
if a check's work grew with the number of entries (as rcan's ``list.pop(0)``
eviction does), the count at 1,000,000 would be far above the count at 10,000.

callgrind counts only inside the compiled ``check`` (``--toggle-collect`` on its
entry point); the fill goes through ``_run``, a different entry point, so only the
saturated checks are counted, including any garbage collection they trigger.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys

from antireplay import WINDOW_BUILD

CHECKS = 20_000
ENTRY_POINT = "CPyPy_ReplayCache___check"  # mypyc's wrapper for ReplayCache.check

WORKLOAD = """
import sys, time
from antireplay import ReplayCache
size, checks = int(sys.argv[1]), int(sys.argv[2])
cache = ReplayCache(window_s=300, max_size=size)
now = time.time()
fill = cache._run  # not the counted entry point
for i in range(size):
    fill(f"fill-{i:012d}", now - 200 + i * (100 / size), 1, None, True)
fresh = [f"new-{i:012d}" for i in range(checks)]
stamps = [now - 99 + i * 1e-4 for i in range(checks)]
check = cache.check
for mid, ts in zip(fresh, stamps):
    check(mid, ts)
"""


def per_check(size: int) -> float:
    """Instructions per saturated check, as callgrind counts them."""
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
            str(CHECKS),
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    found = re.search(r"Collected : (\d+)", run.stderr)
    if found is None:
        raise SystemExit(f"callgrind printed no count:\n{run.stderr[-2000:]}")
    return int(found.group(1)) / CHECKS


def main() -> None:
    if shutil.which("valgrind") is None:
        raise SystemExit("valgrind is needed: apt-get install valgrind")
    if WINDOW_BUILD != "compiled":
        raise SystemExit("this counts the compiled build's entry point; the source build runs")
    small, large = per_check(10_000), per_check(1_000_000)
    print(f"{'entries':>10} {'instructions per check':>24}")
    print(f"{10_000:>10,} {small:>24,.0f}")
    print(f"{1_000_000:>10,} {large:>24,.0f}")
    print(f"work per check at 1,000,000 / at 10,000 entries: {large / small:.2f}x")


if __name__ == "__main__":
    main()
