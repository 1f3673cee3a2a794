"""MemoryStore: the store contract in process memory, with a restart fence."""

from __future__ import annotations

import threading
from collections.abc import Sequence

from antireplay.clock import Clock, resolve
from antireplay.errors import StateUnavailableError

#: Expired entries removed per call: bounded work.
PURGE_BATCH = 64


class MemoryStore:
    """One process; forgets everything on restart, which ``fence()`` makes safe."""

    persistent = False

    def __init__(self, *, clock: Clock | None = None, max_entries: int = 1_000_000) -> None:
        self._started = resolve(clock).wall()
        self.max_entries = max_entries
        self._seen: dict[str, float] = {}
        self._counters: dict[str, int] = {}
        self._lock = threading.Lock()

    def fence(self) -> float:
        return self._started

    def lookup(self, key: str) -> float | None:
        return self._seen.get(key)

    def record(self, key: str, expires_at: float, now: float) -> bool:
        with self._lock:
            return self._record(key, expires_at, now)

    def record_many(self, items: Sequence[tuple[str, float]], now: float) -> list[bool]:
        with self._lock:
            return [self._record(key, exp, now) for key, exp in items]

    def _record(self, key: str, expires_at: float, now: float) -> bool:
        self._purge(now)
        old = self._seen.get(key)
        if old is not None and old >= now:
            return False
        if old is None and len(self._seen) >= self.max_entries:
            raise StateUnavailableError("memory store full; refusing rather than forgetting")
        self._seen.pop(key, None)  # re-insert at the end: keeps insertion ~ expiry order
        self._seen[key] = expires_at
        return True

    def _purge(self, now: float) -> None:
        # Insertion order approximates expiry order; stop at the first live entry.
        for _ in range(PURGE_BATCH):
            key = next(iter(self._seen), None)
            if key is None or self._seen[key] >= now:
                return
            del self._seen[key]

    def advance(self, key: str, value: int) -> bool:
        with self._lock:
            cur = self._counters.get(key)
            if cur is not None and value <= cur:
                return False
            self._counters[key] = value
            return True

    def current(self, key: str) -> int | None:
        return self._counters.get(key)

    def __len__(self) -> int:
        return len(self._seen)

    def close(self) -> None:
        """Nothing to release."""
