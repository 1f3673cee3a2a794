"""The key watcher: a revocation reaches the registry at the next poll, a list not read
for ``PROMISE_S`` fails the registry closed (and says so once), a reload swaps the keys
or keeps them when the file is bad; the lifecycle metrics."""

from __future__ import annotations

import logging
import shutil
import threading
from pathlib import Path

import pytest
from prometheus_client import CollectorRegistry

from antireplay import ManualClock
from antireplay.audit import AuditLog
from antireplay.core.errors import ConfigError, StateUnavailableError
from antireplay.rcan.auth import KeyRegistry
from antireplay.state import StoreSpec
from antireplay.state.revocations import MemoryRevocations, SqliteRevocations, open_revocations
from antireplay.wiring.keys import PROMISE_S, KeyMetrics, KeyWatcher
from harness import until
from harness.envelopes import ED, NOW, registry
from harness.redis_server import RedisServer


class Flaky(MemoryRevocations):
    """A list whose store can be taken down."""

    down = False

    def counters(self) -> dict[str, int]:
        if self.down:
            raise StateUnavailableError("connection refused")
        return super().counters()


def watched(tmp_path: Path, **kwargs: object) -> tuple[KeyWatcher, Flaky, ManualClock]:
    clock = ManualClock(wall=NOW)
    keys = registry()
    keys.clock = clock
    flaky = Flaky()
    audit = AuditLog(tmp_path / "audit.db")
    watcher = KeyWatcher(keys, flaky, audit=audit, clock=clock, **kwargs)  # type: ignore[arg-type]
    return watcher, flaky, clock


def test_a_revocation_reaches_the_registry_at_the_next_poll(tmp_path: Path) -> None:
    watcher, flaky, _ = watched(tmp_path)
    assert not watcher.registry.stale()
    flaky.revoke("op-ed")
    assert watcher.registry.revoked == frozenset()
    watcher.refresh()
    assert watcher.registry.revoked == {"op-ed"}


def test_a_list_not_read_for_the_promise_fails_closed_and_says_so_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    watcher, flaky, clock = watched(tmp_path)
    flaky.down = True
    with caplog.at_level(logging.ERROR, "antireplay.keys"):
        watcher.refresh()
        clock.advance(PROMISE_S / 2)
        watcher.refresh()
        assert not watcher.registry.stale()  # within the promise: the last list holds
        clock.advance(PROMISE_S)
        watcher.refresh()
    assert watcher.registry.stale()
    assert len([r for r in caplog.records if "unreachable" in r.message]) == 1
    flaky.down = False
    watcher.refresh()
    assert not watcher.registry.stale()
    codes = [r.code for r in AuditLog(tmp_path / "audit.db").tail(5)]
    assert codes == ["STATE_UNAVAILABLE", "REVOCATIONS_RESTORED"]


def test_a_list_unreadable_at_start_is_stale_at_once(tmp_path: Path) -> None:
    keys = registry()
    flaky = Flaky()
    flaky.down = True
    KeyWatcher(keys, flaky)
    assert keys.stale()


def test_a_reload_swaps_the_keys_and_a_bad_file_keeps_them(tmp_path: Path) -> None:
    fresh = KeyRegistry()
    fresh.add("op-new", "operator", "ed25519", ED.public_key())
    results: list[KeyRegistry | Exception] = [fresh, ConfigError("file", "x.yaml", "valid YAML")]

    def load() -> KeyRegistry:
        result = results.pop(0)
        if isinstance(result, Exception):
            raise result
        return result

    watcher, flaky, _ = watched(tmp_path, load=load)
    watcher.request_reload()  # what SIGHUP does
    watcher.refresh()
    assert set(watcher.registry.entries) == {"op-new"}
    flaky.request_reload()  # what `antireplay keys reload` does, through the state
    watcher.refresh()
    assert set(watcher.registry.entries) == {"op-new"}
    assert watcher.reloads == {"ok": 1, "failed": 1}


def test_the_metrics_show_seconds_to_expiry_per_kid_and_the_lists_state(tmp_path: Path) -> None:
    watcher, flaky, clock = watched(tmp_path)
    watcher.registry.add("op-soon", "operator", "ed25519", ED.public_key(), not_after=NOW + 3600)
    flaky.revoke("viewer")
    watcher.refresh()
    metrics = CollectorRegistry()
    metrics.register(KeyMetrics(watcher))
    clock.step_wall(600)
    expiry = metrics.get_sample_value("antireplay_key_expiry_seconds", {"kid": "op-soon"})
    assert expiry == pytest.approx(3000)
    assert metrics.get_sample_value("antireplay_keys_revoked") == 1
    assert metrics.get_sample_value("antireplay_revocations_fresh") == 1
    reloads = metrics.get_sample_value("antireplay_key_reloads_total", {"result": "ok"})
    assert reloads == 0


def test_a_state_file_replaced_by_an_older_copy_keeps_the_revocations_and_reseeds_them(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "state.revocations.db"
    store = SqliteRevocations(path)
    store.revoke("op-old")
    store.close()
    old = tmp_path / "old.db"
    shutil.copy(path, old)
    keys = registry()
    watcher = KeyWatcher(keys, SqliteRevocations(path), audit=AuditLog(tmp_path / "audit.db"))
    other = SqliteRevocations(path)
    other.revoke("op-ed")
    other.unrevoke("op-old")
    watcher.refresh()
    assert keys.revoked == {"op-ed"}
    watcher.revocations.close()
    other.close()
    for wal in tmp_path.glob("state.revocations.db-*"):
        wal.unlink()
    shutil.copy(old, path)  # the older copy: op-ed not revoked, op-old revoked, counter smaller
    watcher.revocations = SqliteRevocations(path)
    with caplog.at_level(logging.ERROR, "antireplay.keys"):
        watcher.refresh()
        watcher.refresh()
    assert "op-ed" in keys.revoked  # never un-revoked because the list went backwards
    assert "op-ed" in SqliteRevocations(path).revoked()  # written back for the other replicas
    assert [r.getMessage() for r in caplog.records].count(
        "antireplay: revocation list went backwards; re-seeded 1 kid(s): op-ed"
    ) == 1
    codes = [r.code for r in AuditLog(tmp_path / "audit.db").tail(5)]
    assert codes.count("REVOCATIONS_LOST") == 1
    metrics = CollectorRegistry()
    metrics.register(KeyMetrics(watcher))
    assert metrics.get_sample_value("antireplay_revocations_lost_total") == 1


def test_a_flushed_or_restarted_redis_never_unrevokes_and_the_list_is_reseeded(
    tmp_path: Path,
) -> None:
    server = RedisServer(tmp_path)
    server.start()
    spec = StoreSpec.parse(server.url)
    audit = AuditLog(tmp_path / "audit.db")
    first, second = registry(), registry()
    a = KeyWatcher(first, open_revocations(spec), audit=audit)
    b = KeyWatcher(second, open_revocations(spec), audit=audit)
    try:
        a.revocations.revoke("op-ed")
        for watcher in (a, b):
            watcher.refresh()
        server.client().flushall()
        for watcher in (a, b):
            watcher.refresh()
        assert first.revoked == second.revoked == {"op-ed"}
        assert b.revocations.revoked() == {"op-ed"}  # re-seeded by the first to see the loss
        server.kill()
        server.start()  # no persistence: an empty list
        for watcher in (b, a):
            watcher.refresh()
        assert first.revoked == second.revoked == {"op-ed"}
        assert a.revocations.revoked() == {"op-ed"}
        assert a.lost + b.lost == 2
        codes = [r.code for r in AuditLog(tmp_path / "audit.db").tail(5)]
        assert codes.count("REVOCATIONS_LOST") == 2
    finally:
        a.revocations.close()
        b.revocations.close()
        server.stop()


def test_a_slow_reload_does_not_let_the_revocation_list_go_stale(tmp_path: Path) -> None:
    """A load that takes longer than ``PROMISE_S`` (here 1.5 s of the watcher's clock) runs
    off the poll thread: the polls go on and the registry stays fresh, so no request is
    refused STATE_UNAVAILABLE because keys are being reloaded."""
    started, release = threading.Event(), threading.Event()
    fresh = KeyRegistry()
    fresh.add("op-new", "operator", "ed25519", ED.public_key())

    def slow_load() -> KeyRegistry:
        clock.advance(1.5 * PROMISE_S)  # the load has taken 1.5 s so far
        started.set()
        release.wait(10)
        return fresh

    watcher, _, clock = watched(tmp_path, load=slow_load)
    watcher.start()
    try:
        watcher.request_reload()
        until("the slow load to start", started.is_set, 10)
        until("a poll past the load's 1.5 s", lambda: not watcher.registry.stale(), 3)
    finally:
        release.set()
        until("the reload to end", lambda: watcher.reloads["ok"] == 1, 10)
        watcher.stop()
    assert set(watcher.registry.entries) == {"op-new"}
