"""The memory store's own edges: what it files, and what it refuses to file.

The shared contract (every backend) is in ``test_state.py``; these are the timing wheel's:
slot keys must never collide with the -1 that marks "no slot being drained / filled".
"""

from __future__ import annotations

import math

import pytest

from antireplay.state.memory import MAX_EXPIRY, MemoryStore


@pytest.mark.parametrize("expiry", [-0.1, -0.15, -1.0, math.nan, math.inf, MAX_EXPIRY * 2])
def test_an_expiry_outside_the_wheel_is_refused_and_files_nothing(expiry: float) -> None:
    store = MemoryStore(max_entries=2, restart_fence=False)
    with pytest.raises(ValueError, match="expiry"):
        store.commit("a", expiry, 0.0)
    assert len(store) == 0
    assert store.commit("b", 5.0, 0.2).recorded  # the table is whole: nothing stranded


def test_entries_of_the_first_slot_are_forgotten_and_raise_the_watermark() -> None:
    """Slot 0 (expiries in [0, 0.1)) is a real slot, drained like any other (the head and
    tail markers are -1, below every key a commit can file under)."""
    store = MemoryStore(max_entries=2, restart_fence=False)
    store.commit("a", 0.0, 0.0)
    store.commit("b", 0.05, 0.0)
    assert store.purge(0.2) == 2
    assert len(store) == 0 and store.watermark() == 0.05
    store.commit("c", 5.0, 0.2)
    store.commit("d", 6.0, 0.2)
    assert store.commit("e", 7.0, 0.2).recorded  # full: evicts c, the soonest
    assert store.lookup("c").expiry == -math.inf and store.watermark() == 5.0
