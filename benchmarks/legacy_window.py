"""BASELINE ONLY: the compiled window as it was before issue 12 (main at 37d79ed), unchanged.

``bench_window`` compiles this file with mypyc (cached under ``.benchmarks/``) and times
its store-less ``check`` beside today's ``ReplayCache.commit`` on the memory store: the
issue's goal is that the new split (pure policy + memory store) stays within 1.5x of it.
Nothing in the product imports this file.  It is the old ``src/antireplay/core/window.py``
verbatim except that the store it could call is typed by :class:`LegacyStore` (the old
store contract, gone from ``antireplay.state``) so that it still type-checks.

The original docstring follows.

The freshness window and msg_id seen-set (RCAN §8.3 Replay Attack Prevention).

Theory of operation
-------------------
Rule 1: everything that decides whether an RCAN message is fresh and unique
lives in this file, in :meth:`ReplayCache._run`.  The cache takes values and a
:class:`~antireplay.core.clock.Clock` and returns a verdict; it never reads the
system time, sleeps or does I/O.

A message with timestamp ``ts`` (Unix seconds, the *sender's* clock) and window
``w`` is

* ``MESSAGE_STALE``        when ``now - ts > w``;
* ``MESSAGE_FROM_FUTURE``  when ``ts > now + skew``;
* ``REPLAY_DETECTED``      when its msg_id was accepted before and that entry
  has not expired.

``w`` is ``replay_window_s`` (default 30 s) and ``min(replay_window_s, 10)`` for
SAFETY messages (type 6).  An entry *expires* at ``ts + w`` of the message that
created it, measured on the receiver's wall clock: that is exactly the instant
after which the same message fails the freshness test, so it can be forgotten.
Entries are never keyed on receipt time (a message stamped 4 s in the future
stays fresh 4 s longer than one stamped now), and each entry carries its own
expiry, so a SAFETY message's 10 s window never shortens the life of a
COMMAND's 30 s entry.

Forgetting is monitored by a **low watermark** ``W``: the largest expiry of any
entry ever removed.  A message whose own expiry ``ts + w`` is ``<= W`` might
have had its entry removed, so it is rejected as ``MESSAGE_STALE`` with
``detail="watermark"``.  In normal operation entries are removed only after
they expire, so ``W < now`` and the watermark never rejects a message that
the plain freshness test would accept.  It binds in two situations:

* **Saturation.** At ``max_size`` entries, an entry from the soonest-expiring
  slot (entries are grouped by expiry into 0.1 s slots, a timing wheel: O(1)
  insert and purge, no heap sifting) is dropped and ``W`` rises to its expiry;
  a newcomer that would not outlive that whole slot is refused instead of
  evicting anything.  Memory stays bounded and the cache fails closed: a
  flood can make fresh messages be refused, never make a replay (an exact
  copy, same msg_id and timestamp) pass.  A *new* message that reuses an
  evicted msg_id with a later timestamp can pass: it is not a copy of anything
  captured, since the timestamp is signed.  (We chose ``MESSAGE_STALE`` over
  a separate code so peers need no new handling: resend with a fresh
  timestamp and msg_id; the cause is visible in ``detail`` and in
  ``saturation_evictions``.)
* **Wall-clock steps backwards.** Entries removed before the step stay
  covered by ``W``, so a step back never re-opens a replay.  A forward step
  ages everything early, which only rejects more.

ESTOP invariant: a fresh SAFETY message with ``safety_event == "ESTOP"`` is
always accepted; if its msg_id was seen, or it falls under the watermark, the
verdict carries ``warning="REPLAY_DETECTED"`` (to be audited).  A stale ESTOP
(older than the 10 s safety window) is rejected; STOP and RESUME get no
exemption.

Timestamps are finite, non-negative Unix **seconds**: ``int``/``float`` or a
plain decimal string (``"1700000000.25"``, as the RCAN SDK emits).  Rejected
with ``INVALID_TIMESTAMP``: NaN, ±inf, booleans, ``None``, negatives, exponent
or signed strings, ISO-8601 strings (ambiguous time zones; send Unix seconds),
and values at or above 1e11, which are milliseconds sent in a seconds field
(the RCAN SDK's ``timestamp_ms`` field is converted by the envelope layer,
where its unit is explicit).

Check order inside :meth:`ReplayCache.check`: msg_id shape, timestamp shape,
staleness, future, watermark, duplicate, then commit.  ``precheck`` runs the
same rules and records nothing, so a pipeline can throw replays away before
any cryptography and commit only after authentication.

Speed: a normal install compiles this module with mypyc (``setup.py``;
:mod:`antireplay.core._native` picks the build), so it is written in the style that
compiles to native code: ``Final`` constants, typed attributes, plain ``if``
instead of generic builtins such as ``max``, and the lock's bound methods.  A
slot is a dict of msg_ids (values ``None``); an entry that moves to a later
slot (an extended ESTOP entry) leaves its old filing behind, and forgetting
skips filings whose entry is gone or lives in another slot.  Such dicts hold
no containers, so the garbage collector does not track them and a full
collection never walks the entries.  The slot of the last insert and the
soonest slot are cached, which spares most slot-key lookups.
"""

from __future__ import annotations

import heapq
import math
import re
import threading
from collections.abc import Callable
from typing import Final, Protocol, SupportsFloat, SupportsIndex, final

from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import (
    ConfigError,
    InvalidMessageIdError,
    InvalidTimestampError,
    MessageFromFutureError,
    MessageStaleError,
    ReplayDetectedError,
    StateUnavailableError,
)
from antireplay.core.messages import MessageType, SafetyEvent
from antireplay.core.settings import ALLOWED, SecurityConfig


class LegacyStore(Protocol):
    """The store contract the old window called (``lookup`` returned an expiry or None)."""

    def record(self, key: str, expires_at: float, now: float) -> bool: ...

    def lookup(self, key: str) -> float | None: ...

    def fence(self) -> float: ...


MAX_MSG_ID_LEN: Final = 128
#: Seconds values at or above this are treated as milliseconds sent by mistake (year 5138).
MILLISECONDS_THRESHOLD: Final = 1e11
#: At most this many expired entries are purged per call: bounded work, no latency spikes.
PURGE_BATCH: Final = 64
#: Entries are grouped by expiry into slots of 1/SLOTS_PER_SECOND s (a timing wheel).
SLOTS_PER_SECOND: Final = 10
#: A horizon above every slot key: "forget from the soonest slot, whatever it is".  Slot
#: keys stay below 1e12 (timestamps below 1e11 s); 2**60 is still a machine-sized int in
#: the compiled build, where sys.maxsize would make every comparison a boxed one.
ANY_SLOT: Final = 1 << 60

# Plain constants: enum attribute access costs ~150 ns on the hot path (CPython 3.11).
_SAFETY: Final = int(MessageType.SAFETY)
_ESTOP: Final = str(SafetyEvent.ESTOP)


def is_estop(msg_type: int, safety_event: str | None) -> bool:
    """The ESTOP invariant covers SAFETY messages with the ESTOP event only (inlined in _run)."""
    return msg_type == _SAFETY and safety_event == _ESTOP


_DECIMAL = re.compile(r"[0-9]{1,12}(?:\.[0-9]{1,9})?")
_ISO_HINT = re.compile(r"[0-9]{4}-[0-9]{2}-[0-9]{2}")


@final
class Verdict:
    """An accepted message: when its entry expires and any warning to audit.

    A plain class rather than a NamedTuple: the compiled build allocates it natively
    (a tuple subclass costs ~90 ns per check there) and its attributes are read-only.
    """

    __slots__ = ("expires_at", "msg_id", "timestamp", "warning", "window_s")

    def __init__(
        self,
        msg_id: str,
        timestamp: float,
        window_s: float,
        expires_at: float,
        warning: str | None = None,
    ) -> None:
        self.msg_id: Final = msg_id
        self.timestamp: Final = timestamp
        self.window_s: Final = window_s
        self.expires_at: Final = expires_at
        self.warning: Final = warning

    def __repr__(self) -> str:
        return (
            f"Verdict(msg_id={self.msg_id!r}, timestamp={self.timestamp!r}, "
            f"window_s={self.window_s!r}, expires_at={self.expires_at!r}, warning={self.warning!r})"
        )


def coerce_timestamp(value: object) -> float:
    """Validate a timestamp and return it as float seconds, or raise ``INVALID_TIMESTAMP``."""
    if isinstance(value, bool) or value is None:
        raise InvalidTimestampError(f"timestamp must be Unix seconds, got {type(value).__name__}")
    if isinstance(value, int):
        ts = float(value)
    elif isinstance(value, float):
        ts = value
    elif isinstance(value, str):
        if _DECIMAL.fullmatch(value) is None:
            hint = (
                " (ISO-8601 is not accepted; send Unix seconds)" if _ISO_HINT.match(value) else ""
            )
            raise InvalidTimestampError("timestamp string is not plain decimal seconds" + hint)
        ts = float(value)
    else:
        raise InvalidTimestampError(f"timestamp must be Unix seconds, got {type(value).__name__}")
    if not math.isfinite(ts):
        raise InvalidTimestampError("timestamp must be finite")
    if ts < 0:
        raise InvalidTimestampError("timestamp must not be negative")
    if ts >= MILLISECONDS_THRESHOLD:
        raise InvalidTimestampError(
            "timestamp looks like milliseconds; send seconds (or timestamp_ms in an envelope)"
        )
    return ts


def validate_msg_id(value: object) -> str:
    """A msg_id is a non-empty string of at most 128 characters."""
    if not isinstance(value, str):
        raise InvalidMessageIdError(f"msg_id must be a string, got {type(value).__name__}")
    if not value:
        raise InvalidMessageIdError("msg_id must not be empty")
    if len(value) > MAX_MSG_ID_LEN:
        raise InvalidMessageIdError(f"msg_id longer than {MAX_MSG_ID_LEN} characters")
    return value


class ReplayCache:
    """Bounded, thread-safe freshness window + msg_id seen-set (see the module docstring).

    ``_run`` holds every rule in one place; it is deliberately written as one flat
    function because each Python call costs ~100-300 ns on small robot CPUs.
    """

    def __init__(
        self,
        window_s: SupportsFloat = 30.0,
        max_size: SupportsIndex = 10_000,
        skew_s: SupportsFloat = 5.0,
        clock: Clock | None = None,
        *,
        safety_window_s: SupportsFloat = 10.0,
        store: LegacyStore | None = None,
    ) -> None:
        # Protocol types on purpose: the compiled build checks them here, in _validated,
        # raising ConfigError (key, value, allowed range) instead of a bare TypeError.
        cfg = _validated(window_s, max_size, skew_s, safety_window_s)
        self._store = store
        # Restart fence: a store that may have forgotten accepted messages (a fresh
        # MemoryStore) refuses anything stamped at or before its start time + skew.
        self.fence_rejections = 0
        self.window_s: float = cfg.replay_window_s
        self.safety_window_s: float = min(cfg.safety_window_s, cfg.replay_window_s)
        self.skew_s: float = cfg.skew_s
        self.max_size: int = cfg.msg_id_cache_size
        self._wall: Callable[[], float] = resolve(clock).wall
        self._expiry: dict[str, float] = {}  # msg_id -> expiry of its entry
        # slot key -> {msg_id: None} filed there.  Dicts of str and None hold no containers,
        # so the garbage collector never tracks them: a full collection does not walk
        # every entry (lists would make it: ~30 ms at 1,000,000 entries).  None values
        # cost no allocation (a float would: the compiled build boxes each store apart).
        self._slots: dict[int, dict[str, None]] = {}
        self._slot_keys: list[int] = []  # min-heap of the keys of _slots
        self._tail_key = -1  # the slot that took the last insert (most inserts hit it again)
        self._tail: dict[str, None] = {}
        self._head_key = -1  # the soonest slot, as last looked up by _forget
        self._head: dict[str, None] = {}
        self._watermark = -math.inf
        lock = threading.Lock()
        self._acquire: Callable[[], object] = lock.acquire
        self._release: Callable[[], object] = lock.release
        self.saturation_evictions = 0

    @classmethod
    def from_config(
        cls, config: SecurityConfig, clock: Clock | None = None, store: LegacyStore | None = None
    ) -> ReplayCache:
        """Build a cache from a validated ``security:`` block."""
        return cls(
            config.replay_window_s,
            config.msg_id_cache_size,
            config.skew_s,
            clock,
            safety_window_s=config.safety_window_s,
            store=store,
        )

    def window_for(self, msg_type: int) -> float:
        """SAFETY messages get ``min(replay_window_s, 10)``; others the configured window."""
        return self.safety_window_s if msg_type == _SAFETY else self.window_s

    @property
    def watermark(self) -> float:
        """Largest expiry ever forgotten; messages expiring at or before it are refused."""
        return self._watermark

    def __len__(self) -> int:
        return len(self._expiry)

    def precheck(
        self,
        msg_id: object,
        timestamp: object,
        msg_type: int = MessageType.COMMAND,
        safety_event: str | None = None,
    ) -> Verdict:
        """Apply every rule and record nothing (the pipeline's cheap pre-crypto step)."""
        return self._run(msg_id, timestamp, msg_type, safety_event, False)

    def check(
        self,
        msg_id: object,
        timestamp: object,
        msg_type: int = MessageType.COMMAND,
        safety_event: str | None = None,
    ) -> Verdict:
        """Apply every rule and atomically record the msg_id on acceptance."""
        return self._run(msg_id, timestamp, msg_type, safety_event, True)

    def purge(self) -> int:
        """Forget every expired entry now; returns how many were removed."""
        self._acquire()
        try:
            return self._forget(int(self._wall() * SLOTS_PER_SECOND), len(self._expiry) + 1)
        finally:
            self._release()

    def _run(  # noqa: PLR0912 - one flat function on purpose (see the class docstring)
        self, mid: object, ts: object, msg_type: int, event: str | None, commit: bool
    ) -> Verdict:
        if type(mid) is not str or not 0 < len(mid) <= MAX_MSG_ID_LEN:
            mid = validate_msg_id(mid)
        t = ts if type(ts) is float else coerce_timestamp(ts)
        if not 0.0 <= t < MILLISECONDS_THRESHOLD:
            t = coerce_timestamp(ts)  # raises INVALID_TIMESTAMP with the reason
        safety = msg_type == _SAFETY
        window = self.safety_window_s if safety else self.window_s
        estop = safety and event == _ESTOP
        warning = None
        self._acquire()
        try:
            now = self._wall()
            keys = self._slot_keys
            if commit and keys and keys[0] < now * SLOTS_PER_SECOND - 1:
                self._forget(int(now * SLOTS_PER_SECOND), PURGE_BATCH)
            if now - t > window:
                raise MessageStaleError(f"message is {now - t:.3f}s old; window is {window:g}s")
            if t > now + self.skew_s:
                raise MessageFromFutureError(
                    f"message is {t - now:.3f}s ahead; allowed skew is {self.skew_s:g}s"
                )
            expiry = t + window
            if expiry <= self._watermark:
                if not estop:
                    raise MessageStaleError(
                        "message is older than the replay cache's low watermark",
                        detail="watermark",
                    )
                warning = "REPLAY_DETECTED"
            if self._store is not None:
                warning = (
                    self._shared(mid, ts=t, expiry=expiry, now=now, estop=estop, commit=commit)
                    or warning
                )
            else:
                seen = self._expiry.get(mid)
                if seen is not None and seen >= now:
                    if not estop:
                        raise ReplayDetectedError("msg_id already accepted within its window")
                    warning = "REPLAY_DETECTED"
                if commit and (seen is None or seen < expiry):
                    self._record(mid, expiry, seen is None, estop)
            return Verdict(mid, t, window, expiry, warning)
        finally:
            self._release()

    def _shared(
        self, mid: str, *, ts: float, expiry: float, now: float, estop: bool, commit: bool
    ) -> str | None:
        """The seen-set step against a store; returns a warning for a fresh ESTOP.

        The restart fence is read after the store call, because that call is where
        a store notices it lost its state (a fenced message may then have been
        recorded: harmless, it is refused).  A store that cannot be reached fails
        closed (``STATE_UNAVAILABLE``, 503) for everything except a fresh ESTOP,
        which is processed with a warning: safety beats the replay check's
        availability.
        """
        store = self._store
        assert store is not None
        warning = None
        try:
            if commit:  # one round trip: the atomic record is also the duplicate test
                duplicate = not store.record(mid, expiry, now)
            else:
                seen = store.lookup(mid)
                duplicate = seen is not None and seen >= now
            if ts <= store.fence() + self.skew_s:
                if not estop:
                    self.fence_rejections += 1
                    raise MessageStaleError(
                        "message may predate a restart of the replay state",
                        detail="restart_fence",
                    )
                warning = "REPLAY_DETECTED"
        except StateUnavailableError:
            if estop:
                return "STATE_UNAVAILABLE"
            raise
        if not duplicate:
            return warning
        if not estop:
            raise ReplayDetectedError("msg_id already accepted within its window")
        return "REPLAY_DETECTED"

    def _record(self, mid: str, expires: float, new: bool, force: bool) -> None:
        """File the entry under its expiry slot; when full, evict from the soonest slot.

        An id's entry lives until the latest expiry of any accepted message with that
        id; an entry moved to a later slot leaves its old filing behind, which
        ``_forget`` recognises and skips.  ``force`` (a fresh ESTOP) always records,
        even if that raises the watermark.
        """
        key = int(expires * SLOTS_PER_SECOND)
        if new and len(self._expiry) >= self.max_size:
            # Evicting helps only if the newcomer outlives the whole soonest slot (fail closed).
            if not force and key <= self._slot_keys[0]:
                raise _saturated()
            self._forget(ANY_SLOT, 1)
            self.saturation_evictions += 1
        if key == self._tail_key:
            self._tail[mid] = None
        else:
            slot = self._slots.get(key)
            if slot is None:
                slot = self._slots[key] = {}
                heapq.heappush(self._slot_keys, key)
            slot[mid] = None
            self._tail_key, self._tail = key, slot
        self._expiry[mid] = expires

    def _forget(self, horizon: int, limit: int) -> int:
        """Forget up to ``limit`` live entries, soonest slot first, from slots below ``horizon``.

        The one way entries leave the table (expiry and saturation alike): every forgotten
        expiry raises the watermark, and empty slots are dropped at once, so
        ``_slot_keys[0]`` always names a non-empty slot.
        """
        table, slots, keys, removed = self._expiry, self._slots, self._slot_keys, 0
        while keys and keys[0] < horizon and removed < limit:
            key = keys[0]
            if key != self._head_key:
                self._head_key, self._head = key, slots[key]
            slot = self._head
            while slot and removed < limit:
                mid = slot.popitem()[0]
                expires = table.get(mid)
                if expires is None or int(expires * SLOTS_PER_SECOND) != key:
                    continue  # a filing left behind by an entry forgotten or moved later
                del table[mid]
                removed += 1
                if expires > self._watermark:  # noqa: PLR1730 - max() is a slow generic call
                    self._watermark = expires
            if not slot:
                del slots[heapq.heappop(keys)]
                self._head_key = -1
                if key == self._tail_key:
                    self._tail_key = -1
        return removed


def _saturated() -> MessageStaleError:
    return MessageStaleError(
        "replay cache saturated; message expires before every live entry", detail="watermark"
    )


def _validated(
    window_s: object, max_size: object, skew_s: object, safety_window_s: object
) -> SecurityConfig:
    """Constructor arguments obey the same ranges as the YAML block (no clamping)."""
    if isinstance(max_size, bool) or not isinstance(max_size, int):
        raise ConfigError("max_size", max_size, ALLOWED["msg_id_cache_size"])
    seconds: dict[str, float] = {}
    for key, value in (
        ("replay_window_s", window_s),
        ("skew_s", skew_s),
        ("safety_window_s", safety_window_s),
    ):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(
                "window_s" if key == "replay_window_s" else key, value, "a number of seconds"
            )
        seconds[key] = float(value)
    return SecurityConfig.from_mapping({**seconds, "msg_id_cache_size": max_size})
