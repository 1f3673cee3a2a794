"""A rolled-back audit trail on a real gateway: every audit file copied after 3 commands,
command X accepted, the copy put back (the state database untouched).  The state database
recorded the trail's head with X's row: ``audit verify --state`` and the next ``serve``
start say ``AUDIT_ROLLED_BACK`` (verify exits 1; the start writes a row, counts it in a
metric and says so in ``/readyz`` and the status page).  An exported head proves the same
without the state database (``audit verify --since``)."""

from __future__ import annotations

import json
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import httpx

from antireplay.cli.demo import command, load_operator_key, write_demo_config
from harness import metric, post, serving


def _antireplay(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "antireplay", *map(str, args)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip


def _audit_files(state: Path) -> list[Path]:
    return sorted(p for p in state.iterdir() if p.name.startswith("audit.db"))


def _copy(files: list[Path], to: Path) -> None:
    to.mkdir()
    for file in files:
        shutil.copy2(file, to / file.name)


def _put_back(copy: Path, state: Path) -> None:
    for file in _audit_files(state):
        file.unlink()
    for file in copy.iterdir():
        shutil.copy2(file, state / file.name)


def test_a_trail_put_back_behind_the_state_is_caught_at_start_and_by_verify(
    tmp_path: Path,
) -> None:
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    key = load_operator_key(state)
    audit, db = state / "audit.db", state / "state.db"
    with serving(config) as gateway:
        for i in range(3):
            assert post(gateway, command(key, msg_id=f"cmd-{i}")).status_code == 200
    _copy(_audit_files(state), tmp_path / "copy")
    copied = sqlite3.connect(tmp_path / "copy" / "audit.db")
    (rows,) = copied.execute("SELECT max(seq) FROM audit").fetchone()  # with the start's rows
    copied.close()
    exported = tmp_path / "elsewhere" / "head.json"
    exported.parent.mkdir()
    said = _antireplay("audit", "head", audit, "--export", exported)
    assert said.returncode == 0, said.stderr
    x = command(key, msg_id="command-X")
    with serving(config) as gateway:
        assert post(gateway, x).status_code == 200
    assert _antireplay("audit", "verify", audit, "--state", db).returncode == 0
    assert _antireplay("audit", "verify", audit, "--since", exported).returncode == 0
    later = tmp_path / "elsewhere" / "later.json"
    assert _antireplay("audit", "head", audit, "--export", later).returncode == 0

    _put_back(tmp_path / "copy", state)
    plain = _antireplay("audit", "verify", audit)
    assert plain.returncode == 0  # the copy verifies on its own: that was the blind spot
    checked = _antireplay("audit", "verify", audit, "--state", db)
    assert checked.returncode == 1, checked.stdout
    assert "AUDIT_ROLLED_BACK: against the state database: rolled back" in checked.stdout
    assert f"the trail ends at row {rows}" in checked.stdout
    assert _antireplay("audit", "verify", audit, "--since", exported).returncode == 0
    since = _antireplay("audit", "verify", audit, "--since", later)
    assert since.returncode == 1 and "AUDIT_ROLLED_BACK: against the exported head" in since.stdout

    with serving(config) as gateway:
        ready = httpx.get(f"{gateway.url}/readyz", timeout=10)
        assert ready.status_code == 200  # commands are still served: the replay state holds
        assert ready.json()["warning"].startswith("AUDIT_ROLLED_BACK: behind the state database")
        assert metric(gateway, "antireplay_audit_rolled_back_total") == 1
        page = httpx.get(f"{gateway.url}/status.json", timeout=10).json()
        assert "AUDIT_ROLLED_BACK" in page["warning"]
        assert post(gateway, x).status_code == 409  # the replay state still knows X
    assert gateway.stderr_text is not None and "rolled back" in gateway.stderr_text
    tail = _antireplay("audit", "tail", audit, "--json")
    codes = [json.loads(line)["code"] for line in tail.stdout.splitlines()]
    assert "AUDIT_ROLLED_BACK" in codes


def test_a_rewritten_trail_fails_against_an_exported_head(tmp_path: Path) -> None:
    """A trail rolled back and written on (same row numbers, other rows) is caught too: the
    exported head's row holds another hash."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    key = load_operator_key(state)
    audit = state / "audit.db"
    with serving(config) as gateway:
        assert post(gateway, command(key, msg_id="first")).status_code == 200
    _copy(_audit_files(state), tmp_path / "copy")
    with serving(config) as gateway:
        assert post(gateway, command(key, msg_id="kept")).status_code == 200
    exported = tmp_path / "head.json"
    assert _antireplay("audit", "head", audit, "--export", exported).returncode == 0
    _put_back(tmp_path / "copy", state)
    with serving(config) as gateway:
        assert post(gateway, command(key, msg_id="other")).status_code == 200
    since = _antireplay("audit", "verify", audit, "--since", exported)
    assert since.returncode == 1
    assert "rolled back or rewritten: row" in since.stdout, since.stdout
