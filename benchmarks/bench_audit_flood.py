"""The audit trail under a replay flood: rows and bytes per second, this tree beside an old one.

Run: ``python -m benchmarks audit_flood`` (options ``--seconds=N``, default 20,
``--before=REV``, default :data:`BEFORE`, and ``--max-bytes=N``; or ``python -m
benchmarks.bench_audit_flood --seconds 600 --max-bytes 262144``: the soak).  Needs ``wrk``.

What is measured, and why this way:

* Each tree's gateway is ``antireplay serve --state-dir DIR`` on its embedded default (SQLite
  seen-set and audit trail on disk, fsync on commit, the ``audit:`` defaults' budget), as
  users start it; the old tree is ``git archive REV`` unpacked in a temporary directory (its
  compiled window copied in when this tree has one), run with ``PYTHONPATH`` on its ``src``.
* The flood is what an attacker with captured traffic does: one command accepted once and
  replayed (409 ``REPLAY_DETECTED``) interleaved with commands signed :data:`AGED_S` seconds
  ago, past the replay window (408 ``MESSAGE_STALE``), sent by wrk (one thread, 16
  keep-alive connections, loopback) as fast as the gateway answers.  Every answer must be
  one of those refusals.  This tree floods for ``--seconds``; the old one for at most
  :data:`BEFORE_MAX_S` (rows/s and bytes/s are rates), both durations printed.
* The trail's bytes on disk (segments and WAL, ``du``) are sampled every
  :data:`SAMPLE_S` seconds during the flood, and the peak printed beside the budget.
  ``--max-bytes=N`` runs this tree on the embedded default with ``audit.max_bytes`` N and
  segments of a quarter of it (at least 64 KiB), so a soak sees it rotate and retain.
* Rows and bytes are read after a graceful stop (the summaries of the last interval are
  written then, the WAL checkpointed): rows/s and bytes/s are the growth over the flood (rows
  by row number; bytes by pages, or rows times bytes per row kept once retention removed some);
  then ``antireplay audit verify`` (each tree's own) checks the chain, its verdict printed.
  RSS is the server's resident memory at the flood's end.  The two trees run one after the
  other in the same process, so a noisy neighbour hits both about alike.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import sqlite3
import subprocess
import sys
import tarfile
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

import httpx
import yaml

from antireplay.config import AuditConfig
from antireplay.wiring import embedded_default
from benchmarks._gateway_load import wait_ready
from benchmarks.bench_gateway import WRK_SCRIPT, envelope, signer, stop, wait_healthy, wrk
from benchmarks.bench_gateway import write_lines as write
from harness import free_port

#: ``main`` before the trail was summarised and bounded: the baseline.
BEFORE = "41b328a"
SECONDS = 20
#: The old tree floods at most this long: its figures are rates.
BEFORE_MAX_S = 60
CONNECTIONS = 16
#: Commands signed this long ago: past the default 30 s replay window, so 408.
AGED_S = 120.0
#: Distinct aged commands in the flood (each sent again and again: 408 every time).
AGED = 500
#: Seconds between samples of the trail's bytes on disk.
SAMPLE_S = 2.0
ROOT = Path(__file__).resolve().parents[1]
_JSON = {"Content-Type": "application/json"}
#: The trail's files: the live segment, rotated ones (``audit.db.000041``) and the WAL.
_TRAIL = re.compile(r"audit\.db(\.\d{6,}|-wal)?")
_SEGMENT = re.compile(r"audit\.db(\.\d{6,})?")


@dataclass(frozen=True)
class Flood:
    """One tree's figures under the flood."""

    tree: str
    rps: float
    rows: int
    trail_bytes: int
    rss_mb: float
    seconds: float
    peak_bytes: int
    segments: int
    verdict: str


def old_tree(rev: str, into: Path) -> Path:
    """``git archive REV`` unpacked under ``into``, with this tree's compiled modules."""
    archive = into / "before.tar"
    subprocess.run(["git", "-C", str(ROOT), "archive", "-o", str(archive), rev], check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(into / "before", filter="data")
    for built in (ROOT / "src").rglob("*.so"):
        shutil.copy2(built, into / "before" / built.relative_to(ROOT))
    return into / "before"


def segment_files(state: Path) -> list[Path]:
    return sorted(p for p in state.iterdir() if _SEGMENT.fullmatch(p.name))


def on_disk(state: Path) -> int:
    """The trail's bytes on disk now (``du``: allocated blocks of segments and WAL)."""
    total = 0
    for path in state.iterdir():
        if _TRAIL.fullmatch(path.name):
            try:
                total += path.stat().st_blocks * 512
            except FileNotFoundError:  # rotated or removed between listing and stat
                continue
    return total


@dataclass(frozen=True)
class Trail:
    """The trail now: its last row's number, and the rows and bytes (pages) kept."""

    last: int
    rows: int
    size: int


def trail(state: Path) -> Trail:
    """Read every segment kept (the live one, ``audit.db``, holds the last row)."""
    last = rows = size = 0
    for segment in segment_files(state):
        db = sqlite3.connect(f"file:{segment}?mode=ro", uri=True)
        try:
            count, top = db.execute("SELECT count(*), coalesce(max(seq), 0) FROM audit").fetchone()
            rows, last = rows + int(count), max(last, int(top))
            pages = int(db.execute("PRAGMA page_count").fetchone()[0])
            size += pages * int(db.execute("PRAGMA page_size").fetchone()[0])
        finally:
            db.close()
    return Trail(last, rows, size)


def written(start: Trail, end: Trail) -> tuple[int, int]:
    """Rows and bytes the flood wrote: row numbers run on across segments, so rows are exact;
    bytes are the growth, or, once retention removed rows, rows times bytes per row kept."""
    rows = end.last - start.last
    if end.rows == start.rows + rows:  # nothing removed
        return rows, end.size - start.size
    return rows, rows * end.size // max(end.rows, 1)


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


class Sampler(threading.Thread):
    """The trail's peak bytes on disk, sampled every :data:`SAMPLE_S` until stopped."""

    def __init__(self, state: Path) -> None:
        super().__init__(daemon=True)
        self.state, self.peak, self.done = state, on_disk(state), threading.Event()

    def run(self) -> None:
        while not self.done.wait(SAMPLE_S):
            self.peak = max(self.peak, on_disk(self.state))

    def stop(self) -> int:
        self.done.set()
        self.join()
        return max(self.peak, on_disk(self.state))


def verdict(src: Path, state: Path) -> str:
    """``antireplay audit verify`` of the tree at ``src``: its exit status and what it said."""
    env = {**os.environ, "PYTHONPATH": f"{src}{os.pathsep}{ROOT}"}
    args = [sys.executable, "-m", "antireplay", "audit", "verify", str(state / "audit.db")]
    done = subprocess.run(args, env=env, capture_output=True, text=True, check=False)
    said = [line.strip() for line in (done.stdout or done.stderr).splitlines() if line.strip()]
    return f"exit {done.returncode}: {'; '.join(said)}"


def budget(max_bytes: int | None, state: Path) -> AuditConfig:
    """The ``audit:`` block this tree runs with: the defaults, or ``max_bytes`` in four."""
    if max_bytes is None:
        return AuditConfig(path=str(state / "audit.db"))
    segment = max(64 * 1024, max_bytes // 4)
    return AuditConfig(path=str(state / "audit.db"), segment_bytes=segment, max_bytes=max_bytes)


def configured(state: Path, audit: AuditConfig) -> list[str]:
    """``--config`` for the embedded default under ``state`` with ``audit`` as its trail."""
    config = embedded_default(state).model_dump(mode="json", exclude_defaults=True)
    config["audit"] = audit.model_dump(mode="json")
    path = state / "antireplay.yaml"
    path.write_text(yaml.safe_dump(config))
    return ["--config", str(path)]


def flood(
    tree: str, src: Path, work: Path, seconds: int, audit: AuditConfig | None = None
) -> Flood:
    """Accept one command, then replay it beside aged ones with wrk for ``seconds``."""
    state, port = work / f"{tree}-state", free_port()
    url = f"http://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": f"{src}{os.pathsep}{ROOT}"}
    args = [sys.executable, "-m", "antireplay", "serve", "--state-dir", str(state)]
    args += [] if audit is None else configured(state, audit)
    proc = subprocess.Popen([*args, "--port", str(port)], env=env, stderr=subprocess.DEVNULL)
    try:
        wait_healthy(url, proc, "/healthz")
        wait_ready(url)  # past a new state's first-start fence
        key = signer(state)
        captured = envelope(key)
        httpx.post(url + "/v1/messages", content=captured, headers=_JSON).raise_for_status()
        aged = [envelope(key, AGED_S) for _ in range(AGED)]
        script = write(work / "flood.lua", [WRK_SCRIPT])
        bodies = write(work / "flood.txt", [line for a in aged for line in (captured, a)])
        start = trail(state)
        sampler = Sampler(state)
        sampler.start()
        run = wrk(url, proc.pid, script, bodies, CONNECTIONS, seconds)
        peak = sampler.stop()
        if run.non_2xx != run.requests:
            raise SystemExit(f"{tree}: {run.requests - run.non_2xx} flood requests were accepted")
        rss = rss_mb(proc.pid)
    finally:
        stop(proc)
    rows, size = written(start, trail(state))
    return Flood(
        tree, run.rps, rows, size, rss, seconds,
        max(peak, on_disk(state)), len(segment_files(state)), verdict(src, state),
    )  # fmt: skip


def report(floods: list[Flood], budget: AuditConfig) -> None:
    print(
        f"flood: wrk 1 thread, {CONNECTIONS} connections; one captured command replayed (409)"
        f" interleaved with {AGED} commands signed {AGED_S:.0f} s ago (408)"
    )
    print(
        f"this tree's trail budget: audit.max_bytes {budget.max_bytes} B, "
        f"segment_bytes {budget.segment_bytes} B; trail bytes on disk sampled every {SAMPLE_S} s"
    )
    print(
        f"{'tree':<22} {'s':>4} {'req/s':>7} {'rows/s':>9} {'bytes/s':>11} {'RSS MB':>7} "
        f"{'rows':>9} {'peak B':>11} {'segs':>4}"
    )
    for f in floods:
        print(
            f"{f.tree:<22} {f.seconds:>4.0f} {f.rps:>7.0f} {f.rows / f.seconds:>9.1f} "
            f"{f.trail_bytes / f.seconds:>11.0f} {f.rss_mb:>7.1f} {f.rows:>9} "
            f"{f.peak_bytes:>11} {f.segments:>4}"
        )
    for f in floods:
        print(f"audit verify, {f.tree}: {f.verdict}")
    after = floods[-1]
    if budget.max_bytes is not None:
        within = "within" if after.peak_bytes <= budget.max_bytes else "OVER"
        print(f"this tree's peak trail bytes {after.peak_bytes} B: {within} its budget")
    if len(floods) == 2 and after.rows:
        before = floods[0]
        rows = (before.rows / before.seconds) / (after.rows / after.seconds)
        size = (before.trail_bytes / before.seconds) / max(after.trail_bytes / after.seconds, 1)
        print(f"trail growth per second, before / after: rows x{rows:.0f}, bytes x{size:.0f}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="bench_audit_flood")
    parser.add_argument("--seconds", type=int, default=SECONDS)
    parser.add_argument("--before", default=BEFORE, help="the baseline's git revision")
    parser.add_argument("--max-bytes", type=int, default=None, help="this tree's audit budget")
    options = parser.parse_args(argv or [])
    if shutil.which("wrk") is None:
        raise SystemExit("wrk not found (apt-get install -y wrk)")
    with tempfile.TemporaryDirectory(prefix="antireplay-flood-") as tmp:
        work = Path(tmp)
        before = old_tree(options.before, work)
        before_s = min(options.seconds, BEFORE_MAX_S)
        after = budget(options.max_bytes, work / "after (this tree)-state")
        floods = [
            flood(f"before ({options.before})", before / "src", work, before_s),
            flood("after (this tree)", ROOT / "src", work, options.seconds, after),
        ]
    report(floods, after)


if __name__ == "__main__":
    main(sys.argv[1:])
