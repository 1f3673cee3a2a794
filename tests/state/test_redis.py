"""The Redis store: what it tells an operator when it notices a loss."""

from __future__ import annotations

import logging
import uuid
from functools import partial

import pytest
import redis

from antireplay import ManualClock
from antireplay.core.errors import StateFileError, StateUnavailableError
from antireplay.state.redis import RedisStore
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


def _poisoned(url: str, key: str | None, field: str, value: str) -> RedisStore:
    """A store on a fresh prefix whose meta hash (``key`` None) or entry ``key`` holds
    ``value`` (a hand edit, another program, a torn write)."""
    prefix = f"poison{uuid.uuid4().hex}:"
    store = RedisStore(url, prefix=prefix, clock=ManualClock(wall=NOW))
    store.verify()
    raw = redis.Redis.from_url(url)
    if key is None:
        raw.hset(f"{prefix}{{antireplay}}:meta", field, value)
    else:
        raw.set(store.msg_key(key), value)
    raw.close()
    return store


@pytest.mark.parametrize(
    ("field", "value"), [("fence", "abc"), ("wm", "abc"), ("losses", "abc"), ("fence", "nan")]
)
def test_an_undecodable_meta_field_is_a_state_file_error_naming_the_key(
    redis_url: str, field: str, value: str
) -> None:
    """At start (``verify``) it refuses the start; on a commit or a readiness probe it is
    503; each names the URL, the field and the recovery (drop the meta: the next
    operation fences)."""
    store = _poisoned(redis_url, None, field, value)
    with pytest.raises(StateFileError) as refused:
        store.verify()
    assert refused.value.path == redis_url and f"meta {field}" in refused.value.problem
    assert "DEL" in refused.value.recovery and "meta" in refused.value.recovery
    for op in (partial(store.commit, "cmd", NOW + 60, NOW), store.ready):
        with pytest.raises(StateUnavailableError) as err:
            op()
        assert redis_url in err.value.reason and f"meta {field}" in err.value.reason
    store.close()


def test_an_undecodable_entry_is_503_naming_the_key(redis_url: str) -> None:
    store = _poisoned(redis_url, "cmd", "", "abc")
    for op in (partial(store.lookup, "cmd"), partial(store.commit, "cmd", NOW + 60, NOW)):
        with pytest.raises(StateUnavailableError) as err:
            op()
        assert redis_url in err.value.reason and store.msg_key("cmd") in err.value.reason
    store.close()
