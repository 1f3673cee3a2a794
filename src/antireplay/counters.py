"""Counter-based freshness: sender counters, strict trackers, sliding windows, stream tables.

Theory of operation
-------------------
A counter needs no clock synchronisation: the sender numbers its frames and the
receiver accepts each number at most once.  Four small types, one job each:

* :class:`NonceCounter` (sender): ``next()`` hands out unique, strictly
  increasing values under any number of threads and **never wraps**: at
  ``limit`` (default ``2**64 - 2**13 - 1``, which leaves room for a window of
  8,128 below ``2**64``) it raises :class:`NonceExhaustedError`, and
  :meth:`NonceCounter.persistent` survives restarts and ``kill -9`` by
  persisting a reserved ceiling through :mod:`antireplay.durable` once per
  ``lease`` values: after a crash it resumes above everything it could have
  handed out.  It never reads the clock, so a wall-clock step cannot make it
  repeat.  The file has one owner: a second process (or object) opening it is
  refused while the first holds its lock (see :mod:`antireplay.durable`), since
  two owners would hand out the same values.
* :class:`NonceTracker` (receiver, in-order links): accepts only
  ``n > last_accepted``.
* :class:`CounterWindow` (receiver, lossy/reordering links): the RFC 6479
  sliding bitmap, as WireGuard implements it.  A counter ``c`` is accepted
  once iff ``c < limit`` and ``last - c <= size``.  The bitmap is a ring of
  64-bit words indexed by ``c >> 6``; moving forward clears only the words
  skipped over, so each packet costs O(1) with no shifting.  Counter 0 is
  valid on a fresh window.
* :class:`StreamTable`: one window per (sender, session sequence), bounded.

Every receiver type offers ``check`` (non-mutating, raises a typed error) and
``accept`` (the atomic commit, under a lock).  The caller runs ``check`` before
any cryptography and ``accept`` only after the tag or signature verified, so a
forged far-future counter cannot move the window (no jamming without the key).

Stream eviction never re-opens replay.  Session sequences are assigned by the
receiver in increasing order (see :mod:`antireplay.session`).  When the table
is full, the stream with the **lowest** sequence (the oldest session) is
evicted and a fence rises to its sequence; an unknown stream at or below the
fence is refused with ``SESSION_CLOSED`` and must handshake again, which
yields fresh keys and a fresh sequence.  The evicted stream's captured frames
can therefore never be accepted again.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any

from antireplay.durable import DurableState, as_int, register_repair
from antireplay.errors import (
    CounterLimitError,
    CounterReplayError,
    CounterTooOldError,
    NonceExhaustedError,
    SessionClosedError,
)

#: Sender limit: below 2**64 with room for a full window (WireGuard uses 2**64 - 2**4 - 1).
COUNTER_LIMIT = 2**64 - 2**13 - 1
WORD_BITS = 64
RING_WORDS = 128
#: The RFC 6479 window that a 128-word ring supports: one word is always being recycled.
DEFAULT_WINDOW = (RING_WORDS - 1) * WORD_BITS  # 8128


class NonceCounter:
    """Thread-safe sender counter: unique, strictly increasing, never wraps."""

    def __init__(self, start: int = 1, *, limit: int = COUNTER_LIMIT) -> None:
        if isinstance(start, bool) or not isinstance(start, int) or not 0 <= start < limit:
            raise ValueError(f"start must be an int in [0, {limit}), got {start!r}")
        self._next = start
        self.limit = limit
        self._lock = threading.Lock()
        self._state: DurableState | None = None
        self._ceiling = limit
        self._lease = 0

    @classmethod
    def from_time(cls, *, limit: int = COUNTER_LIMIT) -> NonceCounter:
        """Seed from ``time.time_ns()``, so a restarted sender starts above its last run.

        Only as good as the clock: use :meth:`persistent` where the clock may step back.
        """
        return cls(time.time_ns(), limit=limit)

    @classmethod
    def persistent(
        cls, path: str | os.PathLike[str], lease: int = 1024, *, limit: int = COUNTER_LIMIT
    ) -> NonceCounter:
        """A counter that resumes above every value it could have handed out before a crash."""
        if lease < 1:
            raise ValueError("lease must be >= 1")
        state = DurableState(Path(path), kind="nonce-counter", exclusive=True)
        stored: int | None = state.load(lambda data: as_int(data["ceiling"], "ceiling"))
        ceiling = 0 if stored is None else stored
        if ceiling + 1 >= limit:
            state.release()
            raise NonceExhaustedError(f"persisted counter at {ceiling} has reached its limit")
        counter = cls(ceiling + 1, limit=limit)
        counter._state, counter._lease, counter._ceiling = state, lease, ceiling
        return counter

    def close(self) -> None:
        """Give up the state file (its lock); a later owner resumes above the ceiling."""
        if self._state is not None:
            self._state.release()

    @property
    def peek(self) -> int:
        """The value the next call to :meth:`next` would return."""
        return self._next

    def next(self) -> int:
        """Hand out the next value; raises :class:`NonceExhaustedError` at the limit."""
        with self._lock:
            value = self._next
            if value >= self.limit:
                raise NonceExhaustedError(f"counter reached its limit {self.limit}; rekey")
            if self._state is not None and value > self._ceiling:
                self._reserve(value)
            self._next = value + 1
            return value

    def _reserve(self, value: int) -> None:
        """Persist a new ceiling *before* handing out any value under it."""
        assert self._state is not None
        ceiling = min(value + self._lease - 1, self.limit - 1)
        self._state.save({"ceiling": ceiling})
        self._ceiling = ceiling


class NonceTracker:
    """Receiver for in-order links: accepts only counters above the last accepted one."""

    def __init__(self, last: int = 0) -> None:
        self._last = last
        self._lock = threading.Lock()

    @property
    def last_accepted(self) -> int:
        return self._last

    def check(self, n: int) -> None:
        """Raise :class:`CounterReplayError` unless ``n`` is new; records nothing."""
        if n <= self._last:
            raise CounterReplayError(f"counter {n} is not above {self._last}")

    def accept(self, n: int) -> bool:
        """Commit ``n`` if it is above the last accepted; exactly one winner under races."""
        with self._lock:
            if n <= self._last:
                return False
            self._last = n
            return True


class CounterWindow:
    """RFC 6479 sliding anti-replay window (WireGuard's layout, 128 words of 64 bits)."""

    __slots__ = ("_last", "_lock", "_ring", "limit", "size")

    def __init__(self, size: int = DEFAULT_WINDOW, limit: int = COUNTER_LIMIT) -> None:
        if not 0 < size <= DEFAULT_WINDOW:
            raise ValueError(f"size must be in 1..{DEFAULT_WINDOW}, got {size}")
        self.size = size
        self.limit = limit
        self._last = 0
        self._ring = [0] * RING_WORDS
        self._lock = threading.Lock()

    @property
    def last(self) -> int:
        """The highest counter accepted so far (0 on a fresh window)."""
        return self._last

    def check(self, c: int) -> None:
        """Raise the typed reason ``c`` would be refused; mutates nothing."""
        if not 0 <= c < self.limit:
            raise CounterLimitError(f"counter {c} outside [0, {self.limit})")
        if c > self._last:
            return
        if self._last - c > self.size:
            raise CounterTooOldError(f"counter {c} is behind the window ending at {self._last}")
        if self._ring[(c >> 6) % RING_WORDS] >> (c & 63) & 1:
            raise CounterReplayError(f"counter {c} already accepted")

    def accept(self, c: int) -> bool:
        """Commit ``c``; True iff it was fresh (so a racing duplicate gets False)."""
        if not 0 <= c < self.limit:
            return False
        with self._lock:
            ring, last = self._ring, self._last
            word = c >> 6
            if c > last:
                current = last >> 6
                for i in range(current + 1, current + min(word - current, RING_WORDS) + 1):
                    ring[i % RING_WORDS] = 0
                self._last = c
            elif last - c > self.size:
                return False
            index, bit = word % RING_WORDS, 1 << (c & 63)
            old = ring[index]
            ring[index] = old | bit
            return not old & bit

    def snapshot(self) -> dict[str, Any]:
        """Plain data for persistence (used by stores)."""
        return {"last": self._last, "ring": list(self._ring)}


class StreamTable:
    """Bounded per-stream windows keyed by (sender, session sequence); see the module docstring."""

    def __init__(self, max_streams: int = 1024, window: int = DEFAULT_WINDOW) -> None:
        if max_streams < 1:
            raise ValueError("max_streams must be >= 1")
        self.max_streams = max_streams
        self.window = window
        # None marks a closed stream (a tombstone) until the fence passes its sequence.
        self._streams: dict[tuple[str, int], CounterWindow | None] = {}
        self._fence = -1
        self._lock = threading.Lock()
        self.evictions = 0

    @property
    def fence(self) -> int:
        """Streams with a sequence at or below this, and not in the table, are closed."""
        return self._fence

    def __len__(self) -> int:
        return len(self._streams)

    def check(self, sender: str, seq: int, counter: int) -> None:
        """Cheap pre-crypto check; an unknown stream is judged as a fresh window."""
        key = (sender, seq)
        window = self._streams.get(key)
        if window is None:
            if seq <= self._fence or key in self._streams:
                raise SessionClosedError(f"session {seq} was closed; handshake again")
            if not 0 <= counter < COUNTER_LIMIT:
                raise CounterLimitError(f"counter {counter} out of range")
            return
        window.check(counter)

    def accept(self, sender: str, seq: int, counter: int) -> None:
        """Commit after authentication; creates the stream, evicting the oldest if full."""
        key = (sender, seq)
        with self._lock:
            window = self._streams.get(key)
            if window is None:
                if seq <= self._fence or key in self._streams:
                    raise SessionClosedError(f"session {seq} was closed; handshake again")
                if len(self._streams) >= self.max_streams:
                    self._evict_oldest()
                    if seq <= self._fence:
                        raise SessionClosedError(f"session {seq} is older than every live one")
                window = self._streams[key] = CounterWindow(self.window)
        window.check(counter)
        if not window.accept(counter):
            raise CounterReplayError(f"counter {counter} already accepted")

    def close(self, sender: str, seq: int) -> None:
        """Close a stream for good (after a rekey): later frames get ``SESSION_CLOSED``."""
        with self._lock:
            self._streams[(sender, seq)] = None

    def _evict_oldest(self) -> None:
        oldest = min(self._streams, key=lambda k: k[1])
        del self._streams[oldest]
        self._fence = max(self._fence, oldest[1])
        self.evictions += 1


def _reseed_counter(data: dict[str, Any] | None, now_ns: int) -> dict[str, Any]:
    """A damaged counter file resumes above its salvaged ceiling and above time_ns()."""
    salvaged = data.get("ceiling") if data else None
    floor = salvaged if isinstance(salvaged, int) and not isinstance(salvaged, bool) else 0
    return {"ceiling": max(floor, now_ns)}


register_repair("nonce-counter", _reseed_counter)
