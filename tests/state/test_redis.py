"""The Redis store: what it tells an operator when it notices a loss."""

from __future__ import annotations

import logging

import pytest
import redis

from antireplay import ManualClock
from tests.harness.stores import assert_fenced, fresh_deployment, redis_replicas

NOW = 2_000_000_000.0  # 2033: after any Redis server's real time in these tests


def test_redis_fence_log_line_prints_a_number(
    redis_url: str, caplog: pytest.LogCaptureFixture
) -> None:
    """The loss warning shows the fence as seconds, not Redis's raw reply bytes."""
    clock = ManualClock(wall=NOW)
    (cache,) = redis_replicas(redis_url, 1, clock)
    fresh_deployment(cache, clock)
    captured = clock.wall()
    cache.commit("cmd", captured)
    redis.Redis.from_url(redis_url).flushdb()
    clock.advance(1)
    with caplog.at_level(logging.WARNING, logger="antireplay"):
        assert_fenced(cache, "cmd", captured)
    lines = [r.getMessage() for r in caplog.records if "fence raised to" in r.getMessage()]
    assert lines, caplog.text
    shown = lines[0].rsplit("fence raised to ", 1)[1]
    assert "b'" not in shown
    assert float(shown) > NOW
