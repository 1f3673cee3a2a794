"""Fixes from the operator review of issue 19 (each test fails without its fix)."""

from __future__ import annotations

import inspect
import logging
from pathlib import Path
from types import SimpleNamespace
from typing import cast

import pytest
import redis

from antireplay import ManualClock
from antireplay.audit import AuditLog
from antireplay.pipeline import Receiver
from antireplay.status import _audit, render
from antireplay.stores import open_store
from antireplay.stores.sqlite import SqliteStore
from tests.test_readme import README
from tests.test_status import _snapshot_with
from tests.test_stores import NOW, _assert_fenced, _fresh_deployment, _replicas


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
    """The README's number for how long a command waits on a locked state file is the
    store's own default (and open_store passes no other)."""
    default = inspect.signature(SqliteStore).parameters["timeout_s"].default
    text = " ".join(README.read_text(encoding="utf-8").split())
    assert f"SQLite's busy timeout, {default:g} s (fixed: no configuration knob)" in text
    assert "timeout" not in inspect.getsource(open_store)


def _trail_with_records(path: Path, n: int) -> AuditLog:
    log = AuditLog(path, clock=ManualClock(wall=NOW))
    for i in range(n):
        log.append(at=NOW, outcome="accepted", code=None, warning=None, msg_type=1,
                   sender="operator", sender_verified=True, msg_id=f"m{i}")  # fmt: skip
    return log


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
