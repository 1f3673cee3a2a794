"""Fixes from the operator review of issue 19 (each test fails without its fix)."""

from __future__ import annotations

import inspect
import logging
import os
from pathlib import Path
from types import SimpleNamespace
from typing import cast

import pytest
import redis
from click.testing import CliRunner, Result

from antireplay import ManualClock
from antireplay.audit import AuditLog
from antireplay.cli import main
from antireplay.core.errors import AuditFileError, StateUnavailableError
from antireplay.http.status import _audit, render
from antireplay.rcan.receive import Receiver
from antireplay.state import open_store
from antireplay.state.sqlite import SqliteStore
from tests.e2e.test_readme import DOCUMENTS
from tests.http.test_status import _snapshot_with
from tests.state.test_stores import NOW, _assert_fenced, _fresh_deployment, _replicas


def test_redis_fence_log_line_prints_a_number(
    redis_url: str, caplog: pytest.LogCaptureFixture
) -> None:
    """The loss warning shows the fence as seconds, not Redis's raw reply bytes."""
    clock = ManualClock(wall=NOW)
    (cache,) = _replicas(redis_url, 1, clock)
    _fresh_deployment(cache, clock)
    captured = clock.wall()
    cache.commit("cmd", captured)
    redis.Redis.from_url(redis_url).flushdb()
    clock.advance(1)
    with caplog.at_level(logging.WARNING, logger="antireplay"):
        _assert_fenced(cache, "cmd", captured)
    lines = [r.getMessage() for r in caplog.records if "fence raised to" in r.getMessage()]
    assert lines, caplog.text
    shown = lines[0].rsplit("fence raised to ", 1)[1]
    assert "b'" not in shown
    assert float(shown) > NOW


def test_status_page_names_what_the_window_refusals_table_counts() -> None:
    """The table shows the window's refusals (fence and store included), not every replay:
    a byte-identical copy refused at step 0 is in "Rejected by code" only, so the heading
    says so instead of claiming "Replay refusals"."""
    page = render(_snapshot_with("x"), "nonce")
    assert "Replay refusals by cause" not in page
    assert "Replay-window refusals by cause" in page
    assert "byte-identical copies count under Rejected by code only" in page


def test_readme_states_the_sqlite_busy_timeout_the_store_uses() -> None:
    """The docs' number for how long a command waits on a locked state file is the
    store's own default (and open_store passes no other)."""
    default = inspect.signature(SqliteStore).parameters["timeout_s"].default
    text = " ".join(" ".join(d.read_text(encoding="utf-8") for d in DOCUMENTS).split())
    assert f"SQLite's busy timeout, {default:g} s (fixed: no configuration knob)" in text
    assert "timeout" not in inspect.getsource(open_store)


def _trail_with_records(path: Path, n: int) -> AuditLog:
    log = AuditLog(path, clock=ManualClock(wall=NOW))
    for i in range(n):
        log.append(at=NOW, outcome="accepted", code=None, warning=None, msg_type=1,
                   sender="operator", sender_verified=True, msg_id=f"m{i}")  # fmt: skip
    return log


@pytest.mark.parametrize("key_too", [False, True], ids=["db", "db-and-key"])
def test_a_refused_start_on_a_deleted_trail_creates_nothing(tmp_path: Path, key_too: bool) -> None:
    """``rm audit.db*`` under a running gateway (which rewrites its head afterwards): the next
    start refuses, says the trail was deleted and how many records the head says it held, and
    leaves no new empty trail behind for the start after that to adopt."""
    path = tmp_path / "audit.db"
    _trail_with_records(path, 3).close()
    doomed = [path, *tmp_path.glob("audit.db-*")]
    if key_too:
        doomed.append(tmp_path / "audit.db.key")
    for file in doomed:
        file.unlink()
    with pytest.raises(AuditFileError) as err:
        AuditLog(path)
    assert "deleted" in err.value.problem
    assert "held 3 records" in err.value.problem
    assert not path.exists()


def test_status_says_the_trail_was_deleted_under_the_running_gateway(tmp_path: Path) -> None:
    """Deleted while serving: the status page speaks of the running gateway, not of a start."""
    log = _trail_with_records(tmp_path / "audit.db", 1)
    try:
        (tmp_path / "audit.db").unlink()
        said = _audit(cast(Receiver, SimpleNamespace(audit=log)), 5)["error"]
    finally:
        log.close()
    assert "deleted under the running gateway" in said
    assert "refusing to start" not in said
    assert "audit reanchor" in said


def _config_check(tmp_path: Path, yaml: str) -> Result:
    (tmp_path / "antireplay.yaml").write_text(yaml)
    here = Path.cwd()
    os.chdir(tmp_path)  # the configuration's relative paths, as an operator runs it
    try:
        return CliRunner().invoke(main, ["config", "check", "antireplay.yaml"])
    finally:
        os.chdir(here)


def test_config_check_reaches_the_redis_store(tmp_path: Path) -> None:
    """``config check`` opens the store as ``serve`` does: an unreachable Redis fails it
    with one line naming the store, instead of passing a configuration that cannot start."""
    said = _config_check(tmp_path, "store: redis://127.0.0.1:1/0\naudit: audit.db\n")
    assert said.exit_code == 2, said.output
    errors = [line for line in said.stderr.splitlines() if line.strip()]
    assert len(errors) == 1 and "store redis://127.0.0.1:1/0" in errors[0], said.stderr


def test_config_check_ends_with_a_verdict_and_warns_without_keys(
    tmp_path: Path, redis_url: str
) -> None:
    """A reachable store passes; the last line is the verdict, and a configuration without
    keys (a gateway that refuses everything) is warned about on stderr, still exit 0."""
    said = _config_check(tmp_path, f"store: {redis_url}\naudit: audit.db\n")
    assert said.exit_code == 0, said.output
    assert said.stdout.strip().splitlines()[-1] == f"ok: 0 keys, store {redis_url}, audit audit.db"
    assert "warning" in said.stderr and "no keys" in said.stderr


def test_a_running_writer_refuses_to_append_to_a_deleted_trail(tmp_path: Path) -> None:
    """Deleted under a running writer, a trail would swallow every later record with the
    unlinked file: the append fails (503 for the command) instead of being lost."""
    log = _trail_with_records(tmp_path / "audit.db", 1)
    try:
        for file in tmp_path.glob("audit.db*"):
            file.unlink()
        with pytest.raises(StateUnavailableError, match="deleted or replaced"):
            log.append(at=NOW, outcome="accepted", code=None, warning=None, msg_type=1,
                       sender="operator", sender_verified=True, msg_id="lost")  # fmt: skip
    finally:
        log.close()
