"""MemoryStore: the seen-set in process memory, bounded, with a watermark and a restart fence.

Theory of operation
-------------------
One process, the default for a store-less embed and the fastest backend.  It
keeps the store contract (:mod:`antireplay.state`) with a bounded table:

* **Entries live to their own expiry.**  Entries are grouped by expiry (0 to
  ``MAX_EXPIRY`` seconds; anything else is refused before it is filed) into
  0.1 s slots (a timing wheel: O(1) insert and purge, no heap sifting); each
  commit purges at most ``PURGE_BATCH`` entries from slots that ended before
  ``now``, so the work per call is bounded.
* **Forgetting raises the watermark.**  Every removal, whatever the reason
  (expiry purge, a purge run while the wall clock had stepped forward,
  saturation), raises the watermark to the removed entry's expiry; the window
  refuses any message expiring at or below it.  So a clock step forward and
  back never re-opens a replay, and in normal operation (removal after expiry)
  the watermark stays below ``now`` and refuses nothing the freshness test
  would accept.
* **Bounded by** ``max_entries`` (``msg_id_cache_size``).  A full table evicts
  from the soonest slot (raising the watermark) only for a newcomer that
  outlives that whole slot; otherwise the commit answers ``full`` and the
  window refuses the newcomer (fail closed).  A forced commit (a fresh ESTOP)
  always records.
* **Restart fence.**  A new process has forgotten everything the previous one
  accepted, so the fence is the wall time at construction: the window refuses
  anything stamped at or before ``fence + skew``, which covers every message
  the previous process could have accepted.  The first start is treated the
  same way (nobody can tell a first start from a restart).

A lock makes ``commit`` and ``advance`` atomic across threads; it is never held
across I/O (there is none).  Like the window, this module is compiled with
mypyc in a normal install, hence its style (``Final`` constants, typed
attributes, dicts of ``None`` that the garbage collector does not track; the one
list, the filings of the slot being drained, holds a single slot).
"""

from __future__ import annotations

import heapq
import threading
from collections.abc import Awaitable, Callable, Sequence
from typing import Final

from antireplay.core.clock import Clock, resolve
from antireplay.core.window import NEVER, Seen
from antireplay.state.contract import Offload, offloaded

#: At most this many expired entries are purged per commit: bounded work, no latency spikes.
PURGE_BATCH: Final = 64
#: Entries are grouped by expiry into slots of 1/SLOTS_PER_SECOND s (a timing wheel).
SLOTS_PER_SECOND: Final = 10
#: A horizon above every slot key: "forget from the soonest slot, whatever it is".
ANY_SLOT: Final = 1 << 60
#: Expiries a commit takes, in seconds: a message's timestamp (below 1e11) plus its window.
#: Slot keys are then never negative, and -1 can mean "no slot" (head and tail).
MAX_EXPIRY: Final = 1e12


class MemoryStore:
    """The store contract in process memory (see the module docstring)."""

    backend: Final = "memory"

    def __init__(
        self, *, max_entries: int = 10_000, clock: Clock | None = None, restart_fence: bool = True
    ) -> None:
        if isinstance(max_entries, bool) or not isinstance(max_entries, int) or max_entries < 1:
            raise ValueError("max_entries must be a positive integer")
        self.max_entries: Final = max_entries
        self._fence: Final[float] = resolve(clock).wall() if restart_fence else NEVER
        self._started: Final = self._fence  # every start has no history: fenced as such
        self._watermark: float = NEVER
        self._expiry: dict[str, float] = {}  # msg_id -> expiry of its entry
        # slot key -> {msg_id: None}.  Dicts of str and None hold no containers, so the
        # garbage collector never tracks them: a full collection does not walk the entries.
        self._slots: dict[int, dict[str, None]] = {}
        self._slot_keys: list[int] = []  # min-heap of the keys of _slots
        self._tail_key = -1  # the slot that took the last insert (most inserts hit it again)
        self._tail: dict[str, None] = {}
        self._head_key = -1  # the slot being drained by _forget
        self._head: dict[str, None] = {}  # its dict (emptied; it takes late filings)
        self._drain: list[str] = []  # its filings, moved out of its dict
        self._counters: dict[str, int] = {}
        lock = threading.Lock()
        self._acquire: Callable[[], object] = lock.acquire
        self._release: Callable[[], object] = lock.release
        self.evictions = 0
        self.data_loss_events = 0

    def __len__(self) -> int:
        return len(self._expiry)

    def fence(self) -> float:
        return self._fence

    def watermark(self) -> float:
        return self._watermark

    def verify(self) -> Seen:
        """Nothing to detect in process memory: the fence is the start."""
        return Seen(NEVER, self._watermark, self._fence)

    def lookup(self, key: str) -> Seen:
        expiry = self._expiry.get(key)
        return Seen(NEVER if expiry is None else expiry, self._watermark, self._fence)

    def expiry_of(self, key: str) -> float:
        """The expiry of ``key``'s entry, ``NEVER`` if none (a :meth:`lookup` without its
        ``Seen``: the replay cache's index reads this)."""
        expiry = self._expiry.get(key)
        return NEVER if expiry is None else expiry

    def commit(self, key: str, expires_at: float, now: float, force: bool = False) -> Seen:
        """Record ``key`` unless it has a live entry; a forced commit extends a live one."""
        expiry, watermark, recorded, full = self.commit_fields(key, expires_at, now, force)
        return Seen(expiry, watermark, self._fence, recorded, full)

    def commit_fields(
        self, key: str, expires_at: float, now: float, force: bool = False
    ) -> tuple[float, float, bool, bool]:
        """:meth:`commit` as the fields of its ``Seen``: ``(expiry, watermark, recorded,
        full)`` (the fence is :meth:`fence`, fixed at construction; nothing is ever lost).
        The replay cache's hot path: a compiled caller gets them unboxed, with no object
        allocated."""
        if not 0.0 <= expires_at <= MAX_EXPIRY:  # NaN too: never filed under a bad slot
            raise ValueError(f"expiry {expires_at!r} is not within 0..{MAX_EXPIRY:g} seconds")
        self._acquire()
        try:
            keys = self._slot_keys
            if keys and keys[0] < now * SLOTS_PER_SECOND - 1:
                self._forget(int(now * SLOTS_PER_SECOND), PURGE_BATCH)
            table = self._expiry
            seen = table.get(key)
            if seen is not None and seen >= now:
                if force and seen < expires_at:
                    self._file(key, expires_at)
                return seen, self._watermark, False, False
            watermark = self._watermark  # this commit's own eviction does not apply to itself
            slot_key = int(expires_at * SLOTS_PER_SECOND)
            if seen is None and len(table) >= self.max_entries:
                # Evicting helps only if the newcomer outlives the whole soonest slot.
                if not force and slot_key <= keys[0]:
                    return NEVER, watermark, False, True
                self._forget(ANY_SLOT, 1)
                self.evictions += 1
            if slot_key == self._tail_key:  # _file's common case, inline
                self._tail[key] = None
                table[key] = expires_at
            else:
                self._file(key, expires_at)
            return (NEVER if seen is None else seen), watermark, True, False
        finally:
            self._release()

    def commit_async(
        self,
        key: str,
        expires_at: float,
        now: float,
        force: bool = False,
        offload: Offload | None = None,
    ) -> Awaitable[Seen]:
        """:meth:`commit` from an event loop: run in ``offload`` (it takes the store's lock)."""
        return offloaded(offload, self.commit, key, expires_at, now, force)

    def purge(self, now: float) -> int:
        """Forget every entry expired at ``now``; returns how many were removed."""
        self._acquire()
        try:
            return self._forget(int(now * SLOTS_PER_SECOND), len(self._expiry) + 1)
        finally:
            self._release()

    def _file(self, key: str, expires: float) -> None:
        """File the entry under its expiry slot (an entry moved later leaves its old filing)."""
        slot_key = int(expires * SLOTS_PER_SECOND)
        if slot_key == self._tail_key:
            self._tail[key] = None
        else:
            slot = self._slots.get(slot_key)
            if slot is None:
                slot = self._slots[slot_key] = {}
                heapq.heappush(self._slot_keys, slot_key)
            slot[key] = None
            self._tail_key, self._tail = slot_key, slot
        self._expiry[key] = expires

    def _forget(self, horizon: int, limit: int) -> int:
        """Forget up to ``limit`` live entries, soonest slot first, from slots below ``horizon``.

        The one way entries leave the table: every forgotten expiry raises the
        watermark.  Entering a slot moves its filings into the drain list (popped
        natively, where ``popitem`` is a method call and a tuple per entry); the slot's
        dict stays, empty, to take a late filing, drained in turn.  A drained slot is
        dropped at once, so ``_slot_keys[0]`` always names a slot with filings left.
        """
        table, keys, removed = self._expiry, self._slot_keys, 0
        drain, slot = self._drain, self._head
        while keys and keys[0] < horizon and removed < limit:
            key = keys[0]
            if key != self._head_key:
                if drain:  # a sooner slot was filed ahead of the one draining: refile
                    for mid in drain:
                        slot[mid] = None
                slot = self._head = self._slots[key]
                drain = self._drain = list(slot)
                slot.clear()
                self._head_key = key
            elif not drain:
                drain = self._drain = list(slot)
                slot.clear()
            while drain and removed < limit:
                mid = drain.pop()
                found = table.get(mid)
                if found is None or int(found * SLOTS_PER_SECOND) != key:
                    continue  # a filing left behind by an entry forgotten or moved later
                expires: float = found
                del table[mid]
                removed += 1
                if expires > self._watermark:  # noqa: PLR1730 - max() is a slow generic call
                    self._watermark = expires
            if not drain and not slot:
                del self._slots[heapq.heappop(keys)]
                self._head_key = -1
                if key == self._tail_key:
                    self._tail_key = -1
        return removed

    def advance(self, key: str, value: int) -> bool:
        """Set counter ``key`` to ``value`` iff it is above the current value (or none)."""
        self._acquire()
        try:
            return self._advance(key, value)
        finally:
            self._release()

    def advance_above(self, key: str, value: int, fence_key: str) -> bool:
        """:meth:`advance` iff ``value`` is also above counter ``fence_key`` (one lock)."""
        self._acquire()
        try:
            fence = self._counters.get(fence_key)
            return (fence is None or value > fence) and self._advance(key, value)
        finally:
            self._release()

    def _advance(self, key: str, value: int) -> bool:
        cur = self._counters.get(key)
        if cur is not None and value <= cur:
            return False
        self._counters[key] = value
        return True

    def forget(self, keys: Sequence[str], fence_key: str, fence: int) -> None:
        """Raise counter ``fence_key`` to ``fence`` and drop the counters ``keys``, under
        one lock (the fence itself is never dropped)."""
        self._acquire()
        try:
            self._advance(fence_key, fence)
            for key in keys:
                if key != fence_key:
                    self._counters.pop(key, None)
        finally:
            self._release()

    def current(self, key: str) -> int | None:
        return self._counters.get(key)

    def status(self) -> dict[str, float]:
        """Figures for metrics: entries, watermark, fence, evictions, data-loss events."""
        return {
            "entries": float(len(self._expiry)),
            "watermark": self._watermark,
            "fence": self._fence,
            "evictions": float(self.evictions),
            "data_loss_events": float(self.data_loss_events),
            "no_history_events": 0.0 if self._started == NEVER else 1.0,
        }

    def ready(self) -> None:
        """Process memory always takes a commit (a full table refuses per message)."""

    def close(self) -> None:
        """Nothing to release."""
