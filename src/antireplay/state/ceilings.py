"""Where a :class:`~antireplay.core.counters.NonceCounter` keeps its reserved ceiling.

The counter itself is pure (:mod:`antireplay.core.counters`): it asks a
:class:`~antireplay.core.counters.Ceiling` to durably reserve ``lease`` values
ahead before it hands out any of them, so after a crash it resumes above
everything it could have handed out.  This module holds the two ceilings that
touch state, and the recipes that build a persisted counter:

* :class:`FileCeiling`: a crash-safe state file (:mod:`antireplay.state.durable`),
  locked, so it has one owner; :func:`persistent_counter` opens one by path.
* :class:`StoreCeiling`: a replay store's ``advance`` (atomic on every backend);
  the store contract has no compare-and-set, so owners sharing a store use keys
  of their own.

A damaged counter file is repaired (``antireplay state repair``) by reseeding it
above its salvaged ceiling and above ``time_ns()``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from antireplay.core.counters import COUNTER_LIMIT, NonceCounter
from antireplay.state import ReplayStore
from antireplay.state.durable import DurableState, as_int, register_repair

#: Builds the state-file record for a reserved ceiling (its owner may add fields).
Record = Callable[[int], dict[str, Any]]


def _ceiling_record(ceiling: int) -> dict[str, Any]:
    return {"ceiling": ceiling}


class FileCeiling:
    """The ceiling in a crash-safe state file (:mod:`antireplay.state.durable`), one owner."""

    def __init__(self, state: DurableState, record: Record = _ceiling_record) -> None:
        self.state, self.record = state, record

    def claim(self, value: int, span: int) -> int:
        self.state.save(self.record(value + span - 1))
        return value

    def release(self) -> None:
        self.state.release()


class StoreCeiling:
    """The ceiling in a replay store (``advance``, atomic on every backend), for one owner
    per key; a store that lost data is detected by the owner when it opens."""

    def __init__(self, store: ReplayStore, key: str) -> None:
        self.store, self.key = store, key

    def claim(self, value: int, span: int) -> int:
        value = max(value, (self.store.current(self.key) or 0) + 1)
        while not self.store.advance(self.key, value + span - 1):
            value = max(value, (self.store.current(self.key) or 0) + 1)  # a stray co-owner
        return value

    def release(self) -> None:
        """Nothing to give up: the store outlives its owners."""


def persistent_counter(
    path: str | os.PathLike[str],
    lease: int = 1024,
    *,
    limit: int = COUNTER_LIMIT,
    anchor: Callable[[], int] | None = None,
) -> NonceCounter:
    """A counter that resumes above every value it could have handed out before a crash."""
    state = DurableState(Path(path), kind="nonce-counter", exclusive=True)
    stored: int | None = state.load(lambda data: as_int(data["ceiling"], "ceiling"))
    return counter_on_state(state, 0 if stored is None else stored, lease, limit=limit,
                            anchor=anchor)  # fmt: skip


def counter_on_state(
    state: DurableState,
    ceiling: int,
    lease: int,
    *,
    limit: int = COUNTER_LIMIT,
    anchor: Callable[[], int] | None = None,
    record: Record = _ceiling_record,
) -> NonceCounter:
    """A counter resuming above ``ceiling`` (loaded by the caller from ``state``), that
    saves ``record(ceiling)`` to ``state`` before handing out any value above it."""
    return NonceCounter.on_ceiling(FileCeiling(state, record), ceiling, lease, limit=limit,
                                   anchor=anchor)  # fmt: skip


def _reseed_counter(data: dict[str, Any] | None, now_ns: int) -> dict[str, Any]:
    """A damaged counter file resumes above its salvaged ceiling and above time_ns()."""
    salvaged = data.get("ceiling") if data else None
    floor = salvaged if isinstance(salvaged, int) and not isinstance(salvaged, bool) else 0
    return {"ceiling": max(floor, now_ns)}


register_repair("nonce-counter", _reseed_counter)
