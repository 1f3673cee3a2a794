"""``python -m benchmarks gateway`` runs end to end and ends with its verdicts.

A smoke test, not a measurement: one short round of a few rows on whatever else the
machine is doing; it asserts the benchmark runs against the current tree as users
deploy it (``antireplay serve``, the embedded default), answers what it sends as
expected and prints a PASS or MISS for every row it ran.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

from harness import ROOT


def test_an_unknown_row_is_refused_with_the_list() -> None:
    run = subprocess.run(
        [sys.executable, "-m", "benchmarks", "gateway", "--rows=fresh,nonsense"],
        check=False, cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 2, run.stdout + run.stderr
    assert "nonsense" in run.stderr and "fresh, flood" in run.stderr, run.stderr


def test_a_short_run_prints_a_verdict_for_every_row_it_ran() -> None:
    env = {**os.environ, "PYTHONPATH": f"{ROOT / 'src'}{os.pathsep}{ROOT}"}
    rows = "--rows=fresh,flood,estop,inproc,dds,stages"
    args = [sys.executable, "-m", "benchmarks", "gateway", rows,
            "--rounds=1", "--seconds=1", "--passes=quiet"]  # fmt: skip
    run = subprocess.run(
        args, check=False, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stdout + run.stderr
    out = run.stdout
    assert "load average at start" in out and "load average at end" in out
    assert "FAIL" not in out, out  # every answer as expected (2xx fresh, 409 replays)
    assert "CPU per request, fresh c=32" in out and "inside the gateway" in out, out
    for row in (
        "fresh c=32",
        "flood c=32",
        "ESTOP in flood",
        "in-process",
        "refusals",
        "sealed DDS",
    ):
        assert re.search(rf"^{re.escape(row)} +quiet .* (PASS|MISS)$", out, re.MULTILINE), out
    assert re.search(r"\(40/40\)", out), out  # every ESTOP accepted during the flood
    # The ESTOP row judges the gateway's own figure; the client's is printed beside it.
    estop = re.search(
        r"^ESTOP in flood +quiet +p99 in the gateway .*\n +\(judged inside", out, re.M
    )
    assert estop is not None and "the client's p99 beside it" in out, out
