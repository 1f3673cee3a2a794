"""RedisStore: replay state shared by every gateway replica, failing closed.

* msg_ids: ``SET key expiry NX PX ttl`` (one round trip, atomic); the TTL is
  relative (``ceil((expiry - now) * 1000)`` ms), so the Redis server's wall
  clock does not matter.  Only when the key exists does a Lua script check
  whether its stored expiry already passed on *our* clock (atomic replace).
* counters and epochs: a Lua script compares fixed-width decimal strings and
  advances atomically (Lua numbers are doubles and would round 64-bit values).
* Keys are ``<prefix>{<hash tag>}:m:<msg_id>`` and ``…:c:<name>``: the hash tag
  puts one deployment's keys in one Redis Cluster slot, so pipelines and
  scripts never cross slots.
* A connection pool is shared by all threads; ``record_many`` pipelines a
  batch in one round trip.
* Any connection error or timeout raises ``STATE_UNAVAILABLE`` (HTTP 503): the
  window then refuses everything but a fresh ESTOP.
* **Data loss is detected, not assumed away.**  A sentinel key marks a Redis
  that holds our state.  At start and after every connection error the store
  checks it; if it is missing (a Redis restarted without persistence, a
  flushed or failed-over empty node, or simply a first deployment) the store
  raises its ``fence()`` to the current time, and the window then refuses
  everything stamped before it (plus skew) for one window, exactly like a
  restarted in-memory receiver.  Run Redis with AOF to avoid even that pause.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import redis

from antireplay.clock import Clock, resolve
from antireplay.errors import StateUnavailableError
from antireplay.stores import _codec

T = TypeVar("T")

_REPLACE_EXPIRED = """
local cur = redis.call('GET', KEYS[1])
if cur and tonumber(cur) >= tonumber(ARGV[2]) then return 0 end
redis.call('SET', KEYS[1], ARGV[1], 'PX', ARGV[3])
return 1
"""

_ADVANCE = """
local cur = redis.call('GET', KEYS[1])
if cur and cur >= ARGV[1] then return 0 end
redis.call('SET', KEYS[1], ARGV[1])
return 1
"""


class RedisStore:
    """The store contract on Redis (standalone or Cluster via hash tags)."""

    persistent = True

    def __init__(
        self,
        url: str,
        *,
        prefix: str = "antireplay:",
        hash_tag: str = "antireplay",
        timeout_s: float = 0.5,
        max_connections: int = 64,
        clock: Clock | None = None,
    ) -> None:
        self._pool = redis.ConnectionPool.from_url(
            url,
            socket_timeout=timeout_s,
            socket_connect_timeout=timeout_s,
            max_connections=max_connections,
        )
        self._redis = redis.Redis(connection_pool=self._pool)
        self._base = f"{prefix}{{{hash_tag}}}:"
        self._advance = self._redis.register_script(_ADVANCE)
        self._replace = self._redis.register_script(_REPLACE_EXPIRED)
        self._clock = resolve(clock)
        self._fence = float("-inf")
        self._suspect = True  # verify the sentinel on the first successful call
        self.data_loss_events = 0

    def fence(self) -> float:
        return self._fence

    def msg_key(self, key: str) -> str:
        return f"{self._base}m:{key}"

    def lookup(self, key: str) -> float | None:
        value = self._call(lambda: self._redis.get(self.msg_key(key)))
        return None if value is None else float(value)

    def record(self, key: str, expires_at: float, now: float) -> bool:
        name, ttl = self.msg_key(key), _ttl_ms(expires_at, now)
        if self._call(lambda: self._redis.set(name, repr(expires_at), nx=True, px=ttl)):
            return True
        # Rare path: the key exists; it may be expired by our clock but not yet by Redis's.
        args: list[str | int] = [repr(expires_at), repr(now), ttl]
        return bool(self._call(lambda: self._replace(keys=[name], args=args)))

    def record_many(self, items: Sequence[tuple[str, float]], now: float) -> list[bool]:
        def batch() -> list[Any]:
            pipe = self._redis.pipeline(transaction=False)
            for key, expires_at in items:
                pipe.set(self.msg_key(key), repr(expires_at), nx=True, px=_ttl_ms(expires_at, now))
            return pipe.execute()

        return [bool(r) for r in self._call(batch)]

    def advance(self, key: str, value: int) -> bool:
        encoded = _codec.encode(value)
        return bool(
            self._call(lambda: self._advance(keys=[f"{self._base}c:{key}"], args=[encoded]))
        )

    def current(self, key: str) -> int | None:
        value = self._call(lambda: self._redis.get(f"{self._base}c:{key}"))
        return None if value is None else _codec.decode(value)

    def close(self) -> None:
        self._pool.disconnect()

    def _call(self, op: Callable[[], T]) -> T:
        try:
            if self._suspect:
                self._check_sentinel()
            return op()
        except (redis.ConnectionError, redis.TimeoutError) as exc:
            self._suspect = True
            raise StateUnavailableError(f"redis unreachable: {exc}") from None
        except redis.RedisError as exc:
            self._suspect = True
            raise StateUnavailableError(f"redis error: {exc}") from None

    def _check_sentinel(self) -> None:
        """If our sentinel is gone, Redis lost (or never had) our state: raise the fence."""
        now = self._clock.wall()
        if self._redis.set(f"{self._base}sentinel", repr(now), nx=True):
            self._fence = max(self._fence, now)
            self.data_loss_events += 1
        self._suspect = False


def _ttl_ms(expires_at: float, now: float) -> int:
    """At least 1 ms; rounded up so the key never expires before the message goes stale."""
    return max(1, math.ceil((expires_at - now) * 1000) + 1)
