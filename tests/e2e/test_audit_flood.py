"""The audit trail under a replay flood, on a real small filesystem made by the test.

Each test runs ``antireplay serve`` inside a mount namespace holding an 8 MiB tmpfs
(:mod:`tests.harness.small_fs`) with its replay state and audit trail on it, and speaks to
it over loopback: the flood is fully counted by rows and summaries (metrics agree), the
free-space floors act in order (refusals only counted, then commands refused with
``/readyz`` saying why), and a fresh ESTOP passes a full disk, a trail moved away and a
trail deleted, its row merged into the trail, chained, once the trail is back.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from antireplay.audit import tail, verify
from antireplay.audit.refusals import SUMMARY, summary_count
from antireplay.cli.demo import command, load_operator_key, write_demo_config
from tests.harness import GatewayProcess, metric, post, run_threads, until
from tests.harness.small_fs import SmallFs, small_fs

MIB = 1024 * 1024
SIZE = 8 * MIB
FLOORS = {"min_free_bytes": 3 * MIB, "refuse_free_bytes": 1 * MIB}


@pytest.fixture
def fs(tmp_path: Path) -> Iterator[SmallFs]:
    with small_fs(tmp_path / "small", SIZE) as made:
        yield made


def _gateway(tmp_path: Path, fs: SmallFs) -> GatewayProcess:
    config = write_demo_config(
        tmp_path, store=f"sqlite:{fs.mount / 'state.db'}", audit=str(fs.mount / "audit.db"),
        audit_space=FLOORS,
    )  # fmt: skip
    gateway = GatewayProcess(config, prefix=fs.prefix)
    gateway.start()
    return gateway


def _trail(fs: SmallFs, to: Path) -> Path:
    """A copy of the trail (its files, WAL, head and key) out of the namespace, read while
    the gateway is quiet: SQLite resolves ``/proc/<pid>/root`` to the host's root."""
    to.mkdir(exist_ok=True)
    for name in ("audit.db", "audit.db-wal", "audit.db.head", "audit.db.key"):
        (to / name).unlink(missing_ok=True)
        if fs.host(name).exists():
            shutil.copy2(fs.host(name), to / name)
    return to / "audit.db"


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
            assert metric(http, "antireplay_audit_held_rows") == 0
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
