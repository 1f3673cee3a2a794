"""RedisStore: replay state shared by every gateway replica, failing closed, noticing loss.

Theory of operation
-------------------
* **One script per operation**, atomic on the server: it checks the deployment's
  ``meta`` hash against the server running it, then reads and records the entry or
  counter, returning it with the shared fence and watermark.  So loss is found on
  the very next operation, whether or not the client saw a dropped connection.
  Commits are batched as SQLite groups its fsyncs: ``commit_async`` queues the
  record for a group committer (:mod:`antireplay.state.groupcommit`) whose one
  script call runs the loss checks once and then records every queued entry in
  order (two racers on one key, in one batch or two: exactly one records);
  ``commit`` from a thread is a batch of one.
* **Loss is detected whatever caused it, and fenced for every replica.**  ``meta``
  records who holds our state: the process (``run_id``: a restart, failover,
  restore or slot move changes it) and its replication history (``master_replid``:
  ``REPLICAOF`` elsewhere and back keeps the process, not the data; a master's
  first replica renews it too, which we cannot tell apart); no ``meta`` at all (a new,
  flushed or emptied Redis) is a state with **no history**, fenced alike and said so.
  And the server's ``evicted_keys``: eviction is per key, so entries could go and
  ``meta`` stay; any change of that count (a policy that evicted, put back since) is
  a loss.  A loss raises the **fence** in ``meta`` to ``max(caller's
  now, server time)``, counted once; the fence lives in Redis, so every replica
  applies it.  Not detectable (they need admin rights on Redis): ``DEL`` of one
  entry, and ``CONFIG RESETSTAT`` after an eviction.
* **Eviction is refused**: a ``maxmemory-policy`` other than ``noeviction`` is a
  ``ConfigError`` at start and ``STATE_UNAVAILABLE`` in every script.
* **TTLs run on the server's clock.**  An entry lives until server time
  ``expiry + skew_s`` at least (TTL ``expiry - min(caller's now, server time) +
  skew_s``), so the **watermark** ``server time - skew_s`` covers whatever Redis
  dropped.  A server clock ahead of the caller's beyond ``skew_s`` may expire
  entries early: the script then keeps that watermark in ``meta`` (a loss, counted
  once), so it holds after the clock steps back.  A step forward and back between
  two operations leaves no trace Redis shows us: keep its clock slewed, not stepped.
* **Cluster** (``redis+cluster://``): a hash tag puts all our keys in one slot, so
  the script runs on, and checks, the one node that owns them.  Any connection or
  server error is ``STATE_UNAVAILABLE`` (503): only a fresh ESTOP then passes.
"""

from __future__ import annotations

import contextlib
import functools
import logging
from collections.abc import Callable, Sequence
from typing import Any, Final, TypeVar

import redis
import redis.cluster

from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import ConfigError, StateFileError, StateUnavailableError
from antireplay.core.window import NEVER, Seen
from antireplay.state import _codec
from antireplay.state.contract import Offload
from antireplay.state.groupcommit import GroupCommitter
from antireplay.state.spec import StoreSpec

T = TypeVar("T")
log = logging.getLogger("antireplay.state.redis")

#: "No fence / nothing forgotten" in Redis (Lua's tonumber does not read "-inf").
_FLOOR: Final = "-1e18"
_COMMIT: Final = "commit"
#: A record for the batched commit: msg_id, expiry, the caller's now, force.
_Op = tuple[str, float, float, bool]

_SCRIPT = """
-- ARGV: 1 mode (commit | advance | above | forget | verify), 2 now (a batch's latest),
--       3 skew, 4 floor ("nothing yet"), then: commit: 3 per entry (see below); advance,
--       above, forget: 5 the counter value.  KEYS: 1 meta, then commit: the entries;
--       advance, above, forget: 2 the counter, 3.. the counters to forget (above: 3 the
--       fence counter).
local info = redis.call('INFO', 'server', 'memory', 'stats', 'replication')
-- A field of INFO (a plain find: a pattern scan of the whole text costs far more).
local function field(name)
  local _, stop = string.find(info, '\\n' .. name .. ':', 1, true)
  return stop and string.match(info, '^[%w-]+', stop + 1) or '?'
end
local policy = field('maxmemory_policy')
if policy ~= 'noeviction' then return {-1, policy, '', '', 0} end
-- Who holds our state: this process with this replication history; and its evictions.
local run = field('run_id')
local holder = run .. '/' .. field('master_replid')
local evicted = field('evicted_keys')
local t = redis.call('TIME')
local server_now = tonumber(t[1]) + tonumber(t[2]) / 1000000
local now = tonumber(ARGV[2])
local meta = redis.call('HMGET', KEYS[1], 'run', 'fence', 'wm', 'losses', 'evicted')
local fence, wm, lost = meta[2] or ARGV[4], meta[3] or ARGV[4], 0
-- A stored value that is not a number is never computed with: the client refuses it (-2).
local function number(v) local n = tonumber(v) return n ~= nil and n == n end
if not number(fence) then return {-2, 'fence', fence, '', 0} end
if not number(wm) then return {-2, 'wm', wm, '', 0} end
if meta[4] and not string.match(meta[4], '^%d+$') then return {-2, 'losses', meta[4], '', 0} end
if not meta[1] and not meta[2] then lost = 'new'
elseif meta[1] ~= holder then lost = 'holder'
elseif meta[5] ~= evicted then lost = 'evicted' end
if lost ~= 0 then
  local f = math.max(tonumber(fence), now, server_now)
  fence = string.format('%.6f', f + 0.000001)
  redis.call('HSET', KEYS[1], 'run', holder, 'fence', fence, 'wm', wm, 'evicted', evicted)
  redis.call('HINCRBY', KEYS[1], 'losses', 1)
end
-- A key lives until server time >= its expiry + skew (see the TTL below), so at server
-- time S every entry expiring after S - skew is still here: that is our watermark.  A
-- server clock ahead of the caller's beyond skew may be expiring entries early: keep that
-- watermark in meta (a loss the first time) so it still holds once the clock steps back.
local floor = server_now - tonumber(ARGV[3])
if floor > now then
  if tonumber(wm) < now and lost == 0 then
    lost = 'clock'
    redis.call('HINCRBY', KEYS[1], 'losses', 1)
  end
  wm = string.format('%.6f', math.max(floor, tonumber(wm)))
  redis.call('HSET', KEYS[1], 'wm', wm)
elseif tonumber(wm) < floor then
  wm = string.format('%.6f', floor)
end
if ARGV[1] == 'verify' then return {0, false, fence, wm, lost} end
local skew = tonumber(ARGV[3])
if ARGV[1] == 'commit' then
  -- One batch: per entry key (KEYS 2..) three ARGV from 5: expiry, force, the caller's now.
  -- In order, so two racers on one key in one batch: the first records, the second sees it.
  local out = {0, false, fence, wm, lost}
  for i = 2, #KEYS do
    local a = 5 + (i - 2) * 3
    local cur = redis.call('GET', KEYS[i])
    local recorded = 0
    if cur and not number(cur) then
      recorded = -2
    else
      local expiry, at = tonumber(ARGV[a]), tonumber(ARGV[a + 2])
      local ttl = math.ceil((expiry - math.min(at, server_now) + skew) * 1000) + 1
      if ttl < 1 then ttl = 1 end
      if cur and tonumber(cur) >= at then
        if ARGV[a + 1] == '1' and expiry > tonumber(cur) then
          redis.call('SET', KEYS[i], ARGV[a], 'PX', ttl)
        end
      else
        redis.call('SET', KEYS[i], ARGV[a], 'PX', ttl)
        recorded = 1
      end
    end
    out[#out + 1] = recorded
    out[#out + 1] = cur or false
  end
  return out
end
local cur = redis.call('GET', KEYS[2])
if ARGV[1] == 'forget' then
  for i = 3, #KEYS do if KEYS[i] ~= KEYS[2] then redis.call('DEL', KEYS[i]) end end
end
if ARGV[1] == 'above' then
  local over = redis.call('GET', KEYS[3])
  if over and over >= ARGV[5] then return {0, cur or false, fence, wm, lost} end
end
if cur and cur >= ARGV[5] then return {0, cur, fence, wm, lost} end
redis.call('SET', KEYS[2], ARGV[5])
return {1, cur or false, fence, wm, lost}
"""

#: What the script's loss codes mean, for the log line and ``loss_reason``.
_LOSSES: Final = {
    "new": "no history: no meta for this deployment (a new, flushed or emptied Redis); "
    "fenced like a memory store's start",
    "holder": "another server process or replication history holds it (restart, failover, "
    "REPLICAOF, restore) or it was flushed",
    "evicted": "the server evicted keys (a maxmemory-policy other than noeviction was set "
    "meanwhile) or its statistics were reset",
    "clock": "the server's clock runs ahead of ours beyond skew: it may expire entries early",
}

Client = redis.Redis | redis.cluster.RedisCluster


class RedisStore:
    """The store contract on Redis or Redis Cluster (see the module docstring)."""

    def __init__(
        self,
        url: str,
        *,
        prefix: str = "antireplay:",
        hash_tag: str = "antireplay",
        timeout_s: float = 0.5,
        max_connections: int = 64,
        skew_s: float = 5.0,
        clock: Clock | None = None,
    ) -> None:
        self.url = url
        options: dict[str, Any] = {
            "socket_timeout": timeout_s,
            "socket_connect_timeout": timeout_s,
            "max_connections": max_connections,
        }
        self._redis: Client
        self.backend = "redis"
        spec = StoreSpec.parse(url)
        if spec.backend == "redis-cluster":
            self.backend = "redis-cluster"
            self._redis = redis.cluster.RedisCluster.from_url(spec.target, **options)
        else:
            self._redis = redis.Redis.from_url(url, **options)
        self._base = f"{prefix}{{{hash_tag}}}:"
        self._meta = f"{self._base}meta"
        self._script = self._redis.register_script(_SCRIPT)
        self._clock = resolve(clock)
        self._skew = repr(float(skew_s))
        self._fence = NEVER
        self._watermark = NEVER
        self.data_loss_events = 0
        self.no_history_events = 0
        self.loss_reason: str | None = None
        self._committer: GroupCommitter[_Op, Seen | StateUnavailableError] = GroupCommitter(
            self._commit_batch, name=f"antireplay-redis:{prefix}"
        )
        # Refuse to start on an evicting Redis; if it is down now, every script checks the
        # policy again on the first call that reaches it.
        with contextlib.suppress(redis.ConnectionError, redis.TimeoutError):
            policy = self._evicting_policy()
            if policy is not None:
                raise ConfigError(
                    "store", self.url, f"a Redis with maxmemory-policy noeviction ({policy})"
                )

    def fence(self) -> float:
        return self._fence

    def watermark(self) -> float:
        return self._watermark

    def msg_key(self, key: str) -> str:
        return f"{self._base}m:{key}"

    def lookup(self, key: str) -> Seen:
        """A plain GET (records nothing); fence and watermark as of the last commit."""
        entry = self.msg_key(key)
        value = self._call(lambda: self._redis.get(entry))
        expiry = NEVER if value is None else _codec.serving(lambda: self._expiry(entry, value))
        return Seen(expiry, self._watermark, self._fence)

    def commit(self, key: str, expires_at: float, now: float, force: bool = False) -> Seen:
        """One script call for this one record (a thread's commit: no hand-off)."""
        return _outcome(self._commit_batch([(key, expires_at, now, force)])[0])

    async def commit_async(
        self,
        key: str,
        expires_at: float,
        now: float,
        force: bool = False,
        offload: Offload | None = None,
    ) -> Seen:
        """:meth:`commit` from an event loop: queued for the group committer, whose one
        script call records every record queued meanwhile (no thread held; ``offload`` is
        not needed)."""
        return _outcome(await self._committer.enqueue_async((key, expires_at, now, force)))

    @property
    def group_commit(self) -> GroupCommitter[Any, Any]:
        """The writer that batches this store's async commits (its counters feed /metrics)."""
        return self._committer

    def _commit_batch(self, ops: Sequence[_Op]) -> list[Seen | StateUnavailableError]:
        """One script call for ``ops``: the loss checks once, then each record in order.

        A failure of the store (unreachable, evicting, its meta undecodable) fails the
        batch; an entry that does not decode fails its own record only.
        """
        args = [_COMMIT, repr(max(op[2] for op in ops)), self._skew, _FLOOR]
        keys = [self._meta]
        for key, expires_at, now, force in ops:
            keys.append(self.msg_key(key))
            args += (repr(expires_at), "1" if force else "0", repr(now))
        reply = _codec.serving(lambda: self._reply(keys, args))
        lost = _codec.serving(lambda: self._applied(reply[2], reply[3], reply[4]))
        out: list[Seen | StateUnavailableError] = []
        for i, entry in enumerate(keys[1:]):
            recorded, cur = reply[5 + 2 * i], reply[6 + 2 * i]
            try:
                expiry = _codec.serving(functools.partial(self._held, entry, recorded, cur))
            except StateUnavailableError as exc:
                out.append(exc)
                continue
            out.append(Seen(expiry, self._watermark, self._fence, recorded == 1, False, lost))
            lost = False  # a loss is one event: its flag goes to the batch's first record
        return out

    def _held(self, entry: str, recorded: int, cur: bytes | None) -> float:
        """The expiry a batch found on ``entry`` (``NEVER``: none); one the script found
        undecodable (``recorded == -2``) is refused like an undecodable counter."""
        if recorded == -2:
            raise self._undecodable(entry, cur, "an expiry", also_meta=True)
        return NEVER if cur is None else self._expiry(entry, cur)

    def verify(self) -> Seen:
        """Run the loss and eviction checks alone (start-up, a guard taking its lease)."""
        return self._run("verify", self._meta, self._clock.wall(), "")

    def _reply(self, keys: list[str], args: list[str]) -> list[Any]:
        """Run the script; refuse what it refused to compute with (the batch's failures)."""
        reply: list[Any] = self._call(lambda: self._script(keys=keys, args=args))
        if reply[0] == -1:
            policy = reply[1].decode() if isinstance(reply[1], bytes) else str(reply[1])
            raise StateUnavailableError(
                f"redis {self.url}: {_evicting(policy)}; set it to noeviction"
            )
        if reply[0] == -2:
            field = _text(reply[1])
            raise self._undecodable(f"{self._meta} {field}", reply[2], "a number")
        return reply

    def _run(
        self,
        mode: str,
        key: str,
        now: float,
        value: str,
        *,
        counter: str | None = None,
        forgotten: Sequence[str] = (),
    ) -> Seen:
        """``verify``, ``advance`` or ``forget`` (one key); ``counter`` names the counter."""
        args = [mode, repr(now), self._skew, _FLOOR, value]
        recorded, cur, fence, watermark, lost = self._reply([self._meta, key, *forgotten], args)
        lost = self._applied(fence, watermark, lost)
        if counter is not None and cur is not None:
            self._decode(counter, cur)  # refused: by a counter, never by garbage
        return Seen(NEVER, self._watermark, self._fence, bool(recorded), False, lost)

    def _applied(self, fence: object, watermark: object, lost: object) -> bool:
        """Take the fence and watermark a script returned; a loss it found is counted and
        logged here, once per script call.  Whether it found one."""
        self._fence = _floor(self._number(f"{self._meta} fence", fence))
        self._watermark = _floor(self._number(f"{self._meta} wm", watermark))
        if lost:
            self.data_loss_events += 1
            code = str(_text(lost))
            cause = _LOSSES.get(code, code)
            self.no_history_events += code == "new"
            self.loss_reason = (
                cause if code == "new" else f"redis may have lost our replay state: {cause}"
            )
            raised = ("watermark", self._watermark) if code == "clock" else ("fence", self._fence)
            log.warning("%s: %s; %s raised to %.6f", self.url, self.loss_reason, *raised)
        return bool(lost)

    def advance(self, key: str, value: int) -> bool:
        """Compare-and-advance, with the same loss and eviction checks as a commit."""
        return self._counter("advance", key, value).recorded

    def advance_above(self, key: str, value: int, fence_key: str) -> bool:
        """:meth:`advance` iff ``value`` is also above counter ``fence_key`` (one script)."""
        return self._counter("above", key, value, [f"{self._base}c:{fence_key}"]).recorded

    def forget(self, keys: Sequence[str], fence_key: str, fence: int) -> None:
        """Atomically advance counter ``fence_key`` to at least ``fence`` and delete the
        counters ``keys`` (missing ones are no-ops), with the same loss detection as
        ``advance``; forgetting never re-opens a replay because the fence covers what was
        dropped."""
        self._counter("forget", fence_key, fence, [f"{self._base}c:{k}" for k in keys])

    def _counter(self, mode: str, key: str, value: int, forgotten: Sequence[str] = ()) -> Seen:
        """``advance`` counter ``key`` to ``value`` (``forget``: dropping ``forgotten`` too)."""
        counter, now, encoded = f"{self._base}c:{key}", self._clock.wall(), _codec.encode(value)
        return self._run(mode, counter, now, encoded, counter=key, forgotten=forgotten)

    def current(self, key: str) -> int | None:
        value = self._call(lambda: self._redis.get(f"{self._base}c:{key}"))
        return None if value is None else self._decode(key, value)

    def _decode(self, key: str, value: bytes | str) -> int:
        """A stored counter; one that does not decode names the key and the recovery (drop
        it and the deployment's meta: the next operation raises the restart fence)."""
        drop = f"redis-cli -u {self.url} DEL '{self._base}c:{key}' '{self._meta}'"
        return _codec.decode(value, where=self.url, key=key, recovery=drop)

    def _expiry(self, entry: str, value: bytes | str) -> float:
        """A stored entry's expiry; an undecodable one is refused like an undecodable counter."""
        drop = self._drop(entry, self._meta)
        return _codec.decode_float(_text(value), where=self.url, key=entry, recovery=drop)

    def _number(self, key: str, value: object) -> float:
        """A number of the deployment's meta hash (fence, watermark)."""
        drop = self._drop(self._meta)
        return _codec.decode_float(_text(value), where=self.url, key=key, recovery=drop)

    def _undecodable(
        self, key: str, value: object, expected: str, *, also_meta: bool = False
    ) -> StateFileError:
        """What the script refused to compute with: the entry (dropped with the meta) or
        a field of the meta hash (dropped alone); either way the next operation fences."""
        drop = self._drop(key, self._meta) if also_meta else self._drop(self._meta)
        return _codec.undecodable(_text(value), expected, where=self.url, key=key, recovery=drop)

    def _drop(self, *keys: str) -> str:
        shown = " ".join(f"'{k}'" for k in keys)
        return f"redis-cli -u {self.url} DEL {shown} (the next operation raises the restart fence)"

    def status(self) -> dict[str, float]:
        return {
            "entries": float("nan"),  # not counted: a SCAN per scrape would cost O(n)
            "watermark": self._watermark,
            "fence": self._fence,
            "evictions": 0.0,
            "data_loss_events": float(self.data_loss_events),
            "no_history_events": float(self.no_history_events),
        }

    def close(self) -> None:
        self._committer.close()
        self._redis.close()

    def ready(self) -> None:
        """A read of the deployment's meta (its numbers must decode) and the eviction check
        every commit's script runs (``maxmemory-policy`` changed at run time): what a commit
        needs, recording nothing."""
        meta = self._call(lambda: self._redis.hmget(self._meta, "fence", "wm", "losses"))
        _codec.serving(lambda: self._check_meta(*meta))
        policy = self._call(self._evicting_policy)
        if policy is not None:
            raise StateUnavailableError(f"redis {self.url}: {policy}; set it to noeviction")

    def _check_meta(self, fence: object, wm: object, losses: object) -> None:
        for name, value in (("fence", fence), ("wm", wm)):
            if value is not None:
                self._number(f"{self._meta} {name}", value)
        if losses is not None:
            drop = self._drop(self._meta)
            where, key = self.url, f"{self._meta} losses"
            _codec.decode_int(_text(losses), where=where, key=key, recovery=drop)

    def _evicting_policy(self) -> str | None:
        """Why a node may evict our keys (``maxmemory-policy`` other than noeviction), or None."""
        info: Any = self._redis.info("memory")
        nodes = info.values() if isinstance(self._redis, redis.cluster.RedisCluster) else [info]
        for node in nodes:
            policy = node.get("maxmemory_policy", "noeviction") if isinstance(node, dict) else None
            if policy is not None and policy != "noeviction":
                return _evicting(policy)
        return None

    def _call(self, op: Callable[[], T]) -> T:
        try:
            return op()
        except (redis.ConnectionError, redis.TimeoutError) as exc:
            raise StateUnavailableError(f"redis unreachable: {exc}") from None
        except redis.RedisError as exc:
            raise StateUnavailableError(f"redis error: {exc}") from None


def _outcome(result: Seen | StateUnavailableError) -> Seen:
    """A record's result from a batch: its ``Seen``, or its own failure raised."""
    if isinstance(result, StateUnavailableError):
        raise result
    return result


def _evicting(policy: str) -> str:
    return f"maxmemory-policy {policy} can silently evict replay state"


def _floor(value: float) -> float:
    return NEVER if value <= -1e17 else value


def _text(value: object) -> object:
    """A Redis value (bytes) as the text it holds, for the one decoder of stored values."""
    return value.decode("ascii", "replace") if isinstance(value, bytes) else value
