"""The audit trail under a replay flood: rows and bytes per second, this tree beside an old one.

Run: ``python -m benchmarks audit_flood`` (options ``--seconds=N``, default 20, and
``--before=REV``, default :data:`BEFORE`; or ``python -m benchmarks.bench_audit_flood
--seconds 600``).  Needs ``wrk``.

What is measured, and why this way:

* Each tree's gateway is ``antireplay serve --state-dir DIR`` on its embedded default (SQLite
  seen-set and audit trail on disk, fsync on commit), as users start it; the old tree is
  ``git archive REV`` unpacked in a temporary directory (its compiled window copied in when
  this tree has one), run with ``PYTHONPATH`` on its ``src``.
* The flood is what an attacker with one captured command does: the command is accepted
  once, then replayed by wrk (one thread, 16 keep-alive connections, loopback) as fast as
  the gateway answers, for ``--seconds``.  Every answer must be a 409.
* Trail rows and bytes are read after a graceful stop (the summaries of the last interval
  are written then, the WAL checkpointed into the file): rows/s and bytes/s are the
  growth over the flood's seconds; bytes are the trail's pages (what stays on disk).
  RSS is the server's resident memory at the flood's end.  The two trees run one after the
  other in the same process, so a noisy neighbour hits both about alike.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sqlite3
import subprocess
import sys
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path

import httpx
from tests.harness import free_port

from benchmarks.bench_gateway import WRK_SCRIPT, envelope, signer, stop, wait_healthy, wrk
from benchmarks.bench_gateway import write_lines as write

#: ``main`` before the trail was summarised and bounded: the baseline.
BEFORE = "41b328a"
SECONDS = 20
CONNECTIONS = 16
ROOT = Path(__file__).resolve().parents[1]
_JSON = {"Content-Type": "application/json"}


@dataclass(frozen=True)
class Flood:
    """One tree's figures under the flood."""

    tree: str
    rps: float
    rows: int
    trail_bytes: int
    rss_mb: float
    seconds: float


def old_tree(rev: str, into: Path) -> Path:
    """``git archive REV`` unpacked under ``into``, with this tree's compiled modules."""
    archive = into / "before.tar"
    subprocess.run(["git", "-C", str(ROOT), "archive", "-o", str(archive), rev], check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(into / "before", filter="data")
    for built in (ROOT / "src").rglob("*.so"):
        shutil.copy2(built, into / "before" / built.relative_to(ROOT))
    return into / "before"


def trail_rows(state: Path) -> tuple[int, int]:
    """The trail's rows and bytes (its pages, the WAL's included: what a checkpoint keeps)."""
    db = sqlite3.connect(f"file:{state / 'audit.db'}?mode=ro", uri=True)
    try:
        rows = int(db.execute("SELECT count(*) FROM audit").fetchone()[0])
        pages = int(db.execute("PRAGMA page_count").fetchone()[0])
        return rows, pages * int(db.execute("PRAGMA page_size").fetchone()[0])
    finally:
        db.close()


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def flood(tree: str, src: Path, work: Path, seconds: int) -> Flood:
    """Accept one command, replay it with wrk for ``seconds``; the trail's growth."""
    state, port = work / f"{tree}-state", free_port()
    url = f"http://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": f"{src}{os.pathsep}{ROOT}"}
    args = [sys.executable, "-m", "antireplay", "serve", "--state-dir", str(state)]
    proc = subprocess.Popen([*args, "--port", str(port)], env=env, stderr=subprocess.DEVNULL)
    try:
        wait_healthy(url, proc, "/healthz")
        captured = envelope(signer(state))
        httpx.post(url + "/v1/messages", content=captured, headers=_JSON).raise_for_status()
        script = write(work / "flood.lua", [WRK_SCRIPT])
        bodies = write(work / "flood.txt", [captured])
        rows, size = trail_rows(state)
        run = wrk(url, proc.pid, script, bodies, CONNECTIONS, seconds)
        if run.non_2xx != run.requests:
            raise SystemExit(f"{tree}: {run.requests - run.non_2xx} replays were not refused")
        rss = rss_mb(proc.pid)
    finally:
        stop(proc)
    rows_after, size_after = trail_rows(state)
    return Flood(tree, run.rps, rows_after - rows, size_after - size, rss, seconds)


def report(floods: list[Flood]) -> None:
    print(f"replay flood: wrk 1 thread, {CONNECTIONS} connections, one captured command")
    print(f"{'tree':<22} {'req/s':>7} {'rows/s':>9} {'bytes/s':>11} {'RSS MB':>7} {'rows':>9}")
    for f in floods:
        print(
            f"{f.tree:<22} {f.rps:>7.0f} {f.rows / f.seconds:>9.1f} "
            f"{f.trail_bytes / f.seconds:>11.0f} {f.rss_mb:>7.1f} {f.rows:>9}"
        )
    if len(floods) == 2 and floods[1].rows:
        before, after = floods
        print(
            f"trail growth, before / after: rows x{before.rows / after.rows:.0f}, bytes "
            f"x{before.trail_bytes / max(after.trail_bytes, 1):.0f}"
        )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="bench_audit_flood")
    parser.add_argument("--seconds", type=int, default=SECONDS)
    parser.add_argument("--before", default=BEFORE, help="the baseline's git revision")
    options = parser.parse_args(argv or [])
    if shutil.which("wrk") is None:
        raise SystemExit("wrk not found (apt-get install -y wrk)")
    with tempfile.TemporaryDirectory(prefix="antireplay-flood-") as tmp:
        work = Path(tmp)
        before = old_tree(options.before, work)
        floods = [
            flood(f"before ({options.before})", before / "src", work, options.seconds),
            flood("after (this tree)", ROOT / "src", work, options.seconds),
        ]
    report(floods)


if __name__ == "__main__":
    main(sys.argv[1:])
