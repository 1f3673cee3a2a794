"""Run the fuzz targets under atheris: ``python -m tests.fuzz [TARGET ...] [--seconds N]``.

Each target runs in its own process (libFuzzer exits when it stops), starting
from the seeds in :mod:`tests.fuzz.targets` plus ``tests/corpus/<target>/``, and
growing a working corpus under ``--work`` (default ``.fuzz/``).  A contract
violation (an untyped exception, an HTTP 5xx) stops that target and leaves
``crash-*`` in the work folder: copy it into ``tests/corpus/<target>/`` once
fixed, and the corpus test replays it on every run.  The closing table gives,
per target, the inputs tried, libFuzzer's coverage counters (``cov``: edges,
``ft``: features) and the verdict.  ``pip install -e '.[fuzz]'`` brings atheris.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

from tests.fuzz.targets import TARGETS

ROOT = Path(__file__).resolve().parents[2]
CORPUS = ROOT / "tests" / "corpus"


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.fuzz", description=__doc__)
    parser.add_argument("targets", nargs="*", choices=[*sorted(TARGETS), []], default=[])
    parser.add_argument("--seconds", type=int, default=60, help="time per target")
    parser.add_argument("--runs", type=int, default=-1, help="inputs per target (-1: no cap)")
    parser.add_argument("--work", type=Path, default=ROOT / ".fuzz")
    args = parser.parse_args()
    rows = []
    for name in args.targets or sorted(TARGETS):
        work = args.work / name
        work.mkdir(parents=True, exist_ok=True)
        (CORPUS / name).mkdir(parents=True, exist_ok=True)
        run = subprocess.run(
            [
                sys.executable, "-m", "tests.fuzz.one", name, str(work), str(CORPUS / name),
                f"-max_total_time={args.seconds}", f"-runs={args.runs}",
                f"-artifact_prefix={work}/", "-print_final_stats=1", "-max_len=4096",
            ],
            cwd=ROOT, capture_output=True, text=True, check=False,
        )  # fmt: skip
        log = run.stderr + run.stdout
        (args.work / f"{name}.log").write_text(log)
        done = re.findall(r"Done (\d+) runs", log) or re.findall(r"#(\d+)\s", log)
        cov = re.findall(r"cov: (\d+) ft: (\d+)", log)
        verdict = "ok" if run.returncode == 0 else f"FINDING (exit {run.returncode})"
        inputs = int(done[-1]) if done else 0
        rows.append((name, inputs, *(cov[-1] if cov else ("?", "?")), verdict))
    print(f"{'target':10} {'inputs':>10} {'cov':>6} {'ft':>6}  verdict")
    for name, inputs, edges, features, verdict in rows:
        print(f"{name:10} {inputs:>10} {edges:>6} {features:>6}  {verdict}")
    print(f"{'total':10} {sum(r[1] for r in rows):>10}")
    return 0 if all(r[4] == "ok" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
