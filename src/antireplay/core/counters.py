"""Counter-based freshness: the sender source, sliding windows, fenced high-water tables.

A counter needs no clock synchronisation: the sender numbers its frames, the receiver accepts
each number at most once.  Four types, one job each; every receiver policy is built from them:

* :class:`NonceCounter` (sender): unique, strictly increasing values under any number of
  threads, **never wrapping** (``NonceExhaustedError`` at ``limit``); with an ``anchor``
  (the caller's clock, read before the lock) each value is ``max(last + 1, anchor())``
  (tied to wall time, never repeating on a step back); with a :class:`Ceiling` it
  reserves ``lease`` values durably before handing any out, so it resumes above them
  after ``kill -9`` (ceilings: :mod:`antireplay.state.ceilings`).  Persist, then believe:
  one reservation at a time runs outside the lock, and only a durable one raises the
  ceiling; values below it are handed out meanwhile.
* :class:`CounterWindow` (lossy, reordering links): the RFC 6479 bitmap as WireGuard has it;
  ``c`` is accepted once iff ``0 <= c < limit`` and ``last - c <= size``, O(1) per packet.
* :class:`NonceTracker` (in-order links): strictly above the last accepted value; equal is
  ``COUNTER_REPLAYED``, lower ``COUNTER_TOO_OLD``.
* :class:`FencedTable` (many streams): bounded per-key high-water marks whose evictions raise
  a **fence**; a key not held is admitted only above it, and a full table admits a newcomer
  only above its lowest mark (evicting that key, raising the fence to it), so forgetting
  never re-opens a replay and a refused newcomer evicts nothing (``MESSAGE_STALE``,
  ``detail="fence"``).

Two phases everywhere: ``check`` raises the typed refusal and **records nothing**; ``commit``
runs only after the tag or signature verified (no jamming without the key) and re-checks, so
of two racers exactly one wins.  ``open`` is check, authenticate, commit.  The first three
types lock themselves (no lock is held across I/O); a :class:`FencedTable`'s owner holds a
lock around ``commit``.  Nothing here reads a clock: a time is the caller's argument.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable
from typing import Generic, Protocol, TypeVar

from antireplay.core.errors import (
    CounterExhaustedError,
    CounterReplayedError,
    CounterTooOldError,
    InvalidCounterError,
    MessageStaleError,
    NonceExhaustedError,
    ReplayAttackError,
)

#: Sender limit: below 2**64 with room for a full window (WireGuard uses 2**64 - 2**4 - 1).
COUNTER_LIMIT = 2**64 - 2**13 - 1
WORD_BITS = 64
RING_WORDS = 128
#: The RFC 6479 window that a 128-word ring supports: one word is always being recycled.
DEFAULT_WINDOW = (RING_WORDS - 1) * WORD_BITS  # 8128
#: The ``detail`` of a key refused at a table's eviction fence.
FENCE = "fence"


class Ceiling(Protocol):
    """Where a :class:`NonceCounter` persists the ceiling it reserves ahead of its values."""

    def claim(self, value: int, span: int) -> int:
        """Durably reserve ``[v, v + span)`` for some ``v >= value`` before ``v`` is handed
        out, and return ``v`` (above ``value`` when a co-owner already reserved past it)."""
        ...

    def release(self) -> None:
        """Give up ownership (a file lock); a later owner resumes above the ceiling."""
        ...


class NonceCounter:
    """The sender source: unique, strictly increasing, never wraps; optionally
    wall-anchored and persisted (see the module docstring)."""

    def __init__(
        self,
        start: int = 1,
        *,
        limit: int = COUNTER_LIMIT,
        anchor: Callable[[], int] | None = None,
    ) -> None:
        if isinstance(start, bool) or not isinstance(start, int) or not 0 <= start < limit:
            raise ValueError(f"start must be an int in [0, {limit}), got {start!r}")
        self._next = start
        self.limit = limit
        self._anchor = anchor
        self._lock = threading.Lock()
        #: Signalled when a reservation lands (threads past the ceiling wait for it).
        self._landed = threading.Condition(self._lock)
        self._claiming = False
        #: Bumped by :meth:`restart`: a reservation made for an older binding is not believed.
        self._binding = 0
        self._persist: Ceiling | None = None
        self._ceiling = limit
        self._lease = 0
        #: Ceilings persisted so far (one per ``lease`` values): the write cost, observable.
        self.reservations = 0

    @classmethod
    def from_time(cls, now_ns: int, *, limit: int = COUNTER_LIMIT) -> NonceCounter:
        """Seed from the caller's ``now_ns`` (``time.time_ns()``), so a restarted sender
        starts above its last run.

        Only as good as the clock: use a persisted ceiling where the clock may step back.
        """
        return cls(now_ns, limit=limit)

    @classmethod
    def on_ceiling(
        cls,
        persist: Ceiling,
        ceiling: int,
        lease: int,
        *,
        limit: int = COUNTER_LIMIT,
        anchor: Callable[[], int] | None = None,
    ) -> NonceCounter:
        """A counter resuming above ``ceiling`` that claims ``lease`` values ahead from
        ``persist`` before handing out any value above what it claimed."""
        if lease < 1:
            persist.release()
            raise ValueError("lease must be >= 1")
        if ceiling + 1 >= limit:
            persist.release()
            raise NonceExhaustedError(f"persisted counter at {ceiling} has reached its limit")
        counter = cls(ceiling + 1, limit=limit, anchor=anchor)
        counter.attach(persist, lease)
        return counter

    def attach(self, persist: Ceiling, lease: int) -> None:
        """Persist from now on: claim ``lease`` values ahead from ``persist`` before handing
        out any value above the last one claimed (nothing is claimed yet)."""
        with self._lock:
            self._persist, self._lease, self._ceiling = persist, lease, self._next - 1

    def close(self) -> None:
        """Give up the persisted ceiling (a state file's lock); a later owner resumes above it."""
        if self._persist is not None:
            self._persist.release()

    @property
    def peek(self) -> int:
        """The least value the next call to :meth:`next` can return (the anchor may add)."""
        return self._next

    @property
    def last(self) -> int:
        """The last value handed out (``peek - 1``)."""
        return self._next - 1

    def next(self) -> int:
        """Hand out the next value; raises :class:`NonceExhaustedError` at the limit.  A
        value above the persisted ceiling waits for a durable reservation (made by one
        thread at a time, outside the lock)."""
        floor = 0 if self._anchor is None else self._anchor()
        with self._lock:
            while True:
                value = self._next
                value = floor if floor > value else value  # max() costs a call per value
                if value >= self.limit:
                    raise NonceExhaustedError(f"counter reached its limit {self.limit}; rekey")
                persist = self._persist
                if persist is None or value <= self._ceiling:
                    self._next = value + 1
                    return value
                if not self._claiming:
                    break
                self._landed.wait()
            self._claiming = True
            binding, span = self._binding, min(self._lease, self.limit - value)
        try:
            claimed = persist.claim(value, span)  # the I/O: no lock held
        except BaseException:
            self._landed_at(None, binding)
            raise
        self._landed_at(claimed, binding)
        return self.next()

    def _landed_at(self, claimed: int | None, binding: int) -> None:
        """The reservation is over: durable from ``claimed`` (``None``: it failed, nothing
        believed).  Raise the ceiling to it unless a restart began a new binding meanwhile;
        wake the threads waiting past the ceiling."""
        with self._lock:
            self._claiming = False
            self._landed.notify_all()
            if claimed is None:
                return
            self.reservations += 1
            if claimed >= self.limit:
                raise NonceExhaustedError(f"counter reached its limit {self.limit}; rekey")
            if binding == self._binding:
                # A co-owner may have reserved past the value asked for: skip to ``claimed``.
                self._next = max(self._next, claimed)
                self._ceiling = min(claimed + self._lease - 1, self.limit - 1)

    def restart(self, start: int = 1) -> None:
        """Start over at ``start`` for a **new binding** (the owner changed what the values
        are bound to, e.g. an epoch signer's new prefix).  Values may repeat across
        bindings, never within one; with a state file the next value is persisted first."""
        with self._lock:
            self._next = start
            self._binding += 1
            if self._persist is not None:
                self._ceiling = start - 1


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
        """The highest counter committed so far (0 on a fresh window)."""
        return self._last

    def check(self, c: int) -> None:
        """Raise the typed reason ``c`` would be refused; records nothing."""
        if c < 0:
            raise InvalidCounterError(f"counter {c} is negative")
        if c >= self.limit:
            raise CounterExhaustedError(f"counter {c} at or above the limit {self.limit}; rekey")
        if c > self._last:
            return
        if self._last - c > self.size:
            raise CounterTooOldError(f"counter {c} is behind the window ending at {self._last}")
        if self._ring[(c >> 6) % RING_WORDS] >> (c & 63) & 1:
            raise CounterReplayedError(f"counter {c} already accepted")

    def commit(self, c: int) -> None:
        """Record ``c`` (after authentication); a racing duplicate gets the error ``check``
        would now give."""
        if not self._record(c):
            self.check(c)
            raise CounterReplayedError(f"counter {c} already accepted")

    def _record(self, c: int) -> bool:
        """Set ``c``'s bit under the lock; True iff it was fresh and in range."""
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


class NonceTracker:
    """The strict receiver for in-order links: a value is accepted only if strictly above
    the last one accepted (a :class:`CounterWindow` of width zero).  Locked: of racers on
    one value exactly one wins."""

    __slots__ = ("_last", "_lock", "limit")

    def __init__(self, last: int = 0, limit: int = COUNTER_LIMIT) -> None:
        if isinstance(last, bool) or not isinstance(last, int) or not 0 <= last < limit:
            raise ValueError(f"last must be an int in [0, {limit}), got {last!r}")
        self._last = last
        self.limit = limit
        self._lock = threading.Lock()

    @property
    def last(self) -> int:
        """The last value accepted (``last`` as constructed when none was)."""
        return self._last

    def last_accepted(self) -> int:
        """:attr:`last` under the name CleitonQ's receiver gives it."""
        return self._last

    def check(self, c: int) -> None:
        """Raise the typed reason ``c`` would be refused; records nothing."""
        refusal = self._refusal(c)
        if refusal is not None:
            raise refusal

    def commit(self, c: int) -> None:
        """Record ``c`` (after authentication): compare and swap under the lock, so a racer
        on the same value gets the error ``check`` would now give."""
        with self._lock:
            self.check(c)
            self._last = c

    def accept(self, c: int) -> bool:
        """``check`` and ``commit`` in one atomic step, for a value already authenticated:
        True iff ``c`` was recorded."""
        with self._lock:
            if self._refusal(c) is not None:
                return False
            self._last = c
            return True

    def _refusal(self, c: int) -> ReplayAttackError | None:
        if isinstance(c, bool) or not isinstance(c, int) or c < 0:
            return InvalidCounterError(f"counter {c!r} is not a non-negative integer")
        if c >= self.limit:
            return CounterExhaustedError(f"counter {c} at or above the limit {self.limit}; rekey")
        if c == self._last:
            return CounterReplayedError(f"counter {c} is not above the last accepted ({c})")
        if c < self._last:
            return CounterTooOldError(f"counter {c} is below the last accepted ({self._last})")
        return None


K = TypeVar("K", bound=Hashable)
E = TypeVar("E")


class FencedTable(Generic[K, E]):
    """A bounded table of per-key high-water marks (each with an owner's entry) whose
    evictions raise a fence; see the module docstring.  Not locked: the owner serializes."""

    __slots__ = ("_entries", "_fence", "_marks", "evictions", "max_keys", "what")

    def __init__(self, max_keys: int, *, fence: int = -1, what: str = "stream") -> None:
        if isinstance(max_keys, bool) or not isinstance(max_keys, int) or max_keys < 1:
            raise ValueError("max_keys must be a positive integer")
        self.max_keys = max_keys
        self.what = what
        self._marks: dict[K, int] = {}
        self._entries: dict[K, E] = {}
        self._fence = fence
        self.evictions = 0

    @property
    def fence(self) -> int:
        """Keys the table does not hold are admitted only with a value above this."""
        return self._fence

    def raise_fence(self, value: int) -> None:
        """Raise the fence (restored from persisted state, or a store's loss fence)."""
        self._fence = max(self._fence, value)

    def __len__(self) -> int:
        return len(self._marks)

    def __contains__(self, key: object) -> bool:
        return key in self._marks

    def mark(self, key: K) -> int | None:
        """The key's high-water mark, or None if the table does not hold it."""
        return self._marks.get(key)

    def get(self, key: K) -> E | None:
        """The owner's entry for ``key``, or None."""
        return self._entries.get(key)

    def check(self, key: K, value: int) -> E | None:
        """Records nothing.  The key's entry; for a key the table does not hold, None, and
        ``value`` must be above the fence (else ``MESSAGE_STALE``, ``detail="fence"``).
        The full-table test against the lowest mark is :meth:`commit`'s alone: it scans
        the table, which only an authenticated newcomer may cost (and ``check`` may run
        without the owner's lock, while a commit changes the table)."""
        entry = self._entries.get(key)
        if entry is None and value <= self._fence:
            self._refuse(value, self._fence, "the eviction fence")
        return entry

    def admit(self, key: K, value: int) -> K | None:
        """Records nothing.  Refuses what :meth:`commit` would refuse; else the key a
        commit of ``(key, value)`` would evict (its mark becomes the fence), or None.
        An owner that persists the fence calls this first, then commits once it is
        durable."""
        if key in self._entries:
            return None
        if value <= self._fence:
            self._refuse(value, self._fence, "the eviction fence")
        if len(self._marks) < self.max_keys:
            return None
        marks = self._marks
        lowest = min(marks, key=marks.__getitem__)
        if value <= marks[lowest]:
            self._refuse(value, marks[lowest], "the lowest mark of a full table")
        return lowest

    def commit(self, key: K, value: int, new: Callable[[], E]) -> E:
        """Raise ``key``'s mark to ``value`` (never lowers it).  A key the table does not
        hold is admitted with entry ``new()`` only above the fence and, when the table is
        full, above the lowest mark; only then is that lowest key evicted and the fence
        raised to its mark.  A refused newcomer changes nothing."""
        entry = self._entries.get(key)
        if entry is None:
            lowest = self.admit(key, value)
            if lowest is not None:
                self._fence = max(self._fence, self._marks.pop(lowest))
                del self._entries[lowest]
                self.evictions += 1
            entry = self._entries[key] = new()
            self._marks[key] = value
        elif value > self._marks[key]:
            self._marks[key] = value
        return entry

    def discard(self, key: K) -> E | None:
        """Drop ``key`` *without* raising the fence: only for keys whose values can never
        verify again (a session whose keys are dropped with it)."""
        self._marks.pop(key, None)
        return self._entries.pop(key, None)

    def _refuse(self, value: int, floor: int, what: str) -> None:
        raise MessageStaleError(
            f"new {self.what} at {value}, at or below {what} ({floor})", detail=FENCE
        )
