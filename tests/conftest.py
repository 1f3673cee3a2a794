"""Shared fixtures (helpers live in :mod:`harness`)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from antireplay import ManualClock, ReplayCache, SecurityConfig
from antireplay.audit import AuditLog
from antireplay.rcan.receive import Receiver
from harness import fresh_cache, fresh_receiver
from harness.envelopes import NOW, registry
from harness.redis_server import RedisServer


@pytest.fixture
def impl() -> Callable[..., ReplayCache]:
    """Builds caches as tests need them.  The compiled build runs here; the pure-Python
    build runs the same tests in a subprocess (tests/core/test_native.py)."""
    return fresh_cache


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(wall=NOW)


@pytest.fixture
def receiver(tmp_path: Path, clock: ManualClock) -> Receiver:
    """A Receiver trusting :func:`harness.envelopes.registry`, auditing to ``tmp_path``."""
    return fresh_receiver(
        SecurityConfig(), registry(), None, AuditLog(tmp_path / "audit.db"), clock
    )


@pytest.fixture(scope="session")
def redis_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A real redis-server started for this test session (fails, never skips, if missing)."""
    server = RedisServer(tmp_path_factory.mktemp("redis"))
    server.start()
    try:
        yield server.url
    finally:
        server.stop()
