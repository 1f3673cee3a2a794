"""The audit trail under a replay flood, on a real small filesystem made by the test.

Each test runs ``antireplay serve`` inside a mount namespace holding an 8 MiB tmpfs
(:mod:`harness.small_fs`) with its replay state and audit trail on it, and speaks to
it over loopback: the flood is fully counted by rows and summaries (metrics agree); with a
small ``audit:`` budget, a flood beside fresh commands rotates and retains the trail,
whose bytes on disk stay within the budget throughout and whose chain ``antireplay audit
verify`` proves from where retention cut it; the free-space floors act in order
(refusals only counted, then commands refused with ``/readyz`` saying why), and a fresh
ESTOP passes a full disk, a trail moved away and a trail deleted, its row merged into
the trail, chained, once the trail is back.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from antireplay.audit import tail, verify
from antireplay.audit.refusals import SUMMARY, summary_count
from antireplay.audit.segments import rotated
from antireplay.cli.demo import command, load_operator_key, write_demo_config
from harness import GatewayProcess, metric, post, run_threads, until
from harness.small_fs import SmallFs, small_fs

MIB = 1024 * 1024
SIZE = 8 * MIB
FLOORS = {"min_free_bytes": 3 * MIB, "refuse_free_bytes": 1 * MIB}
SEGMENT = 64 * 1024
BUDGET = 4 * SEGMENT
#: What one group-committed batch may add past the budget before retention runs.
BATCH = 16 * 1024
#: The trail's files on disk: live and rotated segments, the WAL, a rotation's next segment.
_TRAIL = re.compile(r"audit\.db(\.[0-9]{6,}|-wal|\.next)?")


@pytest.fixture
def fs(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[SmallFs]:
    """An 8 MiB tmpfs, or as large as the test asks (``indirect`` parametrization)."""
    with small_fs(tmp_path / "small", getattr(request, "param", SIZE)) as made:
        yield made


def _gateway(tmp_path: Path, fs: SmallFs, **audit: int) -> GatewayProcess:
    config = write_demo_config(
        tmp_path, store=f"sqlite:{fs.mount / 'state.db'}",
        audit={"path": str(fs.mount / "audit.db"), **audit}, audit_space=FLOORS,
    )  # fmt: skip
    gateway = GatewayProcess(config, prefix=fs.prefix)
    gateway.start()
    return gateway


def _trail(fs: SmallFs, to: Path) -> Path:
    """A copy of the trail (its segments, WAL, head and key) out of the namespace, read
    while the gateway is quiet: SQLite resolves ``/proc/<pid>/root`` to the host's root."""
    shutil.rmtree(to, ignore_errors=True)
    to.mkdir()
    for found in fs.host().glob("audit.db*"):
        if not found.name.endswith("-shm"):
            shutil.copy2(found, to / found.name)
    return to / "audit.db"


def _on_disk(fs: SmallFs) -> int:
    """The trail's bytes on disk now, as ``du`` counts them: its segments, WAL and a
    rotation's next segment, each file once (a rotation hard-links the live one)."""
    files = {}
    for found in fs.host().glob("audit.db*"):
        if _TRAIL.fullmatch(found.name):
            try:
                st = found.stat()
            except FileNotFoundError:  # removed by retention since the listing
                continue
            files[st.st_ino] = st.st_size
    return sum(files.values())


class _Peak(threading.Thread):
    """The peak of the trail's bytes, by ``du`` and by the gateway's metric, until stopped."""

    def __init__(self, fs: SmallFs, gateway: GatewayProcess) -> None:
        super().__init__(daemon=True)
        self.fs, self.gateway, self.done = fs, gateway, threading.Event()
        self.du = self.metric = self.samples = 0

    def run(self) -> None:
        with httpx.Client(base_url=self.gateway.url, timeout=10) as http:
            while not self.done.is_set():
                self.du = max(self.du, _on_disk(self.fs))
                self.metric = max(self.metric, int(metric(http, "antireplay_audit_trail_bytes")))
                self.samples += 1

    def __enter__(self) -> _Peak:
        self.start()
        return self

    def __exit__(self, *_: object) -> None:
        self.done.set()
        self.join()


def _counted(trail: Path, code: str) -> int:
    """Refusals of ``code`` the trail stands for: its rows, and each summary's count."""
    return sum(summary_count(r.outcome, r.warning) for r in tail(trail, 100_000) if r.code == code)


def test_a_replay_flood_is_fully_counted_by_rows_and_summaries(tmp_path: Path, fs: SmallFs) -> None:
    gateway = _gateway(tmp_path, fs)
    raw = command(load_operator_key(tmp_path))
    try:
        with httpx.Client(base_url=gateway.url, timeout=10) as http:
            assert post(http, raw).status_code == 200

            def flood(_: int) -> None:
                with httpx.Client(base_url=gateway.url, timeout=10) as own:
                    for _ in range(75):
                        assert post(own, raw).status_code == 409

            run_threads(8, flood)
            code = '{code="REPLAY_DETECTED"}'
            assert metric(http, "antireplay_rejected_total", code) == 600
            assert metric(http, "antireplay_audit_trail_bytes") < 1 * MIB
    finally:
        gateway.stop()
    trail = _trail(fs, tmp_path / "out")
    assert _counted(trail, "REPLAY_DETECTED") == 600  # summaries written at shutdown
    rows = tail(trail, 100_000)
    assert sum(r.outcome == SUMMARY for r in rows) >= 1 and len(rows) < 100
    assert verify(trail).ok


def _verify_cli(fs: SmallFs) -> subprocess.CompletedProcess[str]:
    """``antireplay audit verify`` on the trail where the gateway wrote it (in the namespace)."""
    args = [*fs.prefix, sys.executable, "-m", "antireplay", "audit", "verify",
            str(fs.mount / "audit.db")]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    return subprocess.run(args, capture_output=True, text=True, timeout=60, env=env, check=False)


@pytest.mark.parametrize("fs", [16 * MIB], indirect=True)  # the replay state's WAL takes 4
def test_a_flood_beside_fresh_commands_rotates_and_retains_the_trail_within_budget(
    tmp_path: Path, fs: SmallFs
) -> None:
    """Fresh commands fill a 256 KiB budget of 64 KiB segments; then replays and aged
    commands flood the gateway beside more fresh ones.  Sampled throughout, the trail's
    bytes on disk stay within the budget plus one batch; every refusal counted in metrics
    is a row or in a summary kept; an ESTOP on the full disk passes and is merged."""
    gateway = _gateway(tmp_path, fs, segment_bytes=SEGMENT, max_bytes=BUDGET)
    key = load_operator_key(tmp_path)
    live = fs.host("audit.db")
    raw = command(key)
    aged = [command(key, age_s=120) for _ in range(8)]
    try:
        with httpx.Client(base_url=gateway.url, timeout=10) as http, _Peak(fs, gateway) as peak:
            assert post(http, raw).status_code == 200

            def fresh(n: int) -> None:
                with httpx.Client(base_url=gateway.url, timeout=10) as own:
                    for _ in range(n):
                        assert post(own, command(key)).status_code == 200

            run_threads(8, lambda _: fresh(300))  # rotations, then retention
            first = rotated(live)[0][0]
            assert first > 1  # retention removed the oldest segments already
            marker = command(key, msg_id="flood-starts")
            assert post(http, marker).status_code == 200

            def flood(i: int) -> None:
                with httpx.Client(base_url=gateway.url, timeout=10) as own:
                    for n in range(100):
                        if i % 4 == 0:  # half a budget of fresh rows: the marker's is kept
                            assert post(own, command(key)).status_code == 200
                        assert post(own, raw).status_code == 409
                        assert post(own, aged[(i + n) % 8]).status_code == 408

            run_threads(8, flood)  # 800 replays, 800 aged, 200 fresh
            assert rotated(live)[0][0] > first  # the flood rotated and retained too
            assert metric(http, "antireplay_audit_disk_pressure") == 0  # all refusals had room
            replays = metric(http, "antireplay_rejected_total", '{code="REPLAY_DETECTED"}')
            stale = metric(http, "antireplay_rejected_total", '{code="MESSAGE_STALE"}')
            assert (replays, stale) == (800, 800)
        assert peak.samples > 10
        assert peak.du <= BUDGET and peak.metric <= BUDGET, (peak.du, peak.metric)

        with httpx.Client(base_url=gateway.url, timeout=10) as http:
            fs.fill(leave=0)  # full: the ESTOP's row is spilled, then merged
            halt = command(key, type=6, safety_event="ESTOP", cmd="halt")
            assert post(http, halt).status_code == 200
            fs.drain()
            until("ready again", lambda: http.get("/readyz").status_code == 200)
            assert post(http, command(key)).status_code == 200  # merges the spilled row
            until("spill merged", lambda: metric(http, "antireplay_audit_held_rows") == 0)
    finally:
        gateway.stop()
    said = _verify_cli(fs)
    assert said.returncode == 0, said.stdout + said.stderr
    assert "removed by retention; chain verified from row" in said.stdout, said.stdout
    copy = _trail(fs, tmp_path / "out")
    report = verify(copy)
    assert report.ok and report.first_segment > first
    rows = tail(copy, 100_000)
    assert report.first_row > 1  # retention cut the fill
    kept = {r.msg_id for r in rows}
    assert json.loads(marker)["msg_id"] in kept  # the flood's rows are all kept: fully counted
    assert (_counted(copy, "REPLAY_DETECTED"), _counted(copy, "MESSAGE_STALE")) == (800, 800)
    assert sum(r.outcome == SUMMARY for r in rows) >= 2
    assert json.loads(halt)["msg_id"] in kept


def test_below_the_floors_refusals_are_counted_then_commands_refused_and_estops_pass(
    tmp_path: Path, fs: SmallFs
) -> None:
    gateway = _gateway(tmp_path, fs)
    key = load_operator_key(tmp_path)
    trail = fs.host("audit.db")
    out = tmp_path / "out"
    try:
        with httpx.Client(base_url=gateway.url, timeout=10) as http:
            raw = command(key)
            assert post(http, raw).status_code == 200
            fs.fill(leave=2 * MIB)  # below the first floor
            until("the first floor", lambda: metric(http, "antireplay_audit_disk_pressure") == 1)
            rows = len(tail(_trail(fs, out), 100_000))
            for _ in range(30):
                assert post(http, raw).status_code == 409
            assert len(tail(_trail(fs, out), 100_000)) == rows  # counted, not written
            assert metric(http, "antireplay_rejected_total", '{code="REPLAY_DETECTED"}') == 30
            assert post(http, command(key)).status_code == 200  # acceptances still recorded

            fs.fill(leave=MIB // 2)  # below the second floor
            until("the second floor", lambda: http.get("/readyz").status_code == 503)
            assert "disk" in http.get("/readyz").json()["reason"]
            refused = post(http, command(key))
            assert (refused.status_code, refused.json()["code"]) == (503, "STATE_UNAVAILABLE")
            assert "disk" in refused.json()["reason"]
            estop = command(key, type=6, safety_event="ESTOP", cmd="estop")
            assert post(http, estop).status_code == 200

            fs.fill(leave=0)  # full: the store and the trail fail, the ESTOP's row is spilled
            halt = command(key, type=6, safety_event="ESTOP", cmd="halt")
            assert post(http, halt).status_code == 200
            assert metric(http, "antireplay_audit_spilled_estops_total") == 1
            assert post(http, command(key)).status_code == 503

            fs.drain()  # space back (the store on the same disk takes commits again)
            aside = fs.host("aside.db")
            trail.rename(aside)  # the trail moved away: the ESTOP's row is spilled
            moved = command(key, type=6, safety_event="ESTOP", cmd="stop")
            answer = post(http, moved)
            assert (answer.status_code, answer.json()["warning"]) == (200, "AUDIT_UNAVAILABLE")
            assert metric(http, "antireplay_audit_spilled_estops_total") == 2

            aside.rename(trail)  # back
            until("ready again", lambda: http.get("/readyz").status_code == 200)
            assert post(http, command(key)).status_code == 200  # merges the spilled row
            until("spill merged", lambda: metric(http, "antireplay_audit_held_rows") == 0)
    finally:
        gateway.stop()
    copy = _trail(fs, out)
    ids = {json.loads(m)["msg_id"]: m for m in (halt, moved)}
    spilled = [r for r in tail(copy, 100_000) if r.msg_id in ids]
    assert [(r.msg_id, r.outcome) for r in spilled] == [(i, "accepted") for i in ids]
    assert [r.warning for r in spilled] == ["STATE_UNAVAILABLE", "AUDIT_UNAVAILABLE"]
    assert verify(copy).ok


def test_an_estop_passes_with_the_trail_deleted_and_is_merged_after_its_restore(
    tmp_path: Path, fs: SmallFs
) -> None:
    gateway = _gateway(tmp_path, fs)
    key = load_operator_key(tmp_path)
    trail = fs.host("audit.db")
    try:
        with httpx.Client(base_url=gateway.url, timeout=10) as http:
            assert post(http, command(key)).status_code == 200
            backup = _trail(fs, tmp_path / "backup")  # quiet: every answered row is durable
            trail.unlink()
            estop = command(key, type=6, safety_event="ESTOP", cmd="estop")
            answer = post(http, estop)
            assert (answer.status_code, answer.json()["warning"]) == (200, "AUDIT_UNAVAILABLE")
            assert post(http, command(key)).status_code == 503
    finally:
        gateway.stop()
    for name in ("audit.db-wal", "audit.db-shm"):
        fs.host(name).unlink(missing_ok=True)
    for name in ("audit.db", "audit.db-wal"):
        if (backup.parent / name).exists():
            shutil.copy2(backup.parent / name, fs.host(name))
    gateway.start()  # merges the spilled row at open
    gateway.stop()
    copy = _trail(fs, tmp_path / "out")
    rows = [r for r in tail(copy, 100) if r.msg_id == json.loads(estop)["msg_id"]]
    assert [(r.outcome, r.warning) for r in rows] == [("accepted", "AUDIT_UNAVAILABLE")]
    assert verify(copy).ok
