"""Shared fixtures (helpers live in :mod:`harness`)."""

from __future__ import annotations

import contextlib
import weakref
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from antireplay import ManualClock, ReplayCache, SecurityConfig
from antireplay.audit import AuditLog
from antireplay.rcan.receive import Receiver
from harness import fresh_cache, fresh_receiver
from harness.envelopes import NOW, registry
from harness.redis_server import RedisServer

#: Every audit trail opened in this process, weakly: a test's own are closed when it ends.
_TRAILS: weakref.WeakSet[AuditLog] = weakref.WeakSet()
_open_trail = AuditLog.__init__


def _tracked_init(self: AuditLog, *args: Any, **kwargs: Any) -> None:
    _open_trail(self, *args, **kwargs)
    _TRAILS.add(self)


AuditLog.__init__ = _tracked_init  # type: ignore[method-assign]


@pytest.fixture(autouse=True)
def _trails_closed() -> Iterator[None]:
    """Close the audit trails a test opened and left open (an app never shut down, a
    receiver never closed): their writer threads would keep their files open for the rest
    of the run, and past 1,024 descriptors pymavlink's ``select()`` fails in later tests."""
    before = set(map(id, _TRAILS))
    yield
    for trail in [t for t in _TRAILS if id(t) not in before]:
        with contextlib.suppress(Exception):
            trail.close()


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
