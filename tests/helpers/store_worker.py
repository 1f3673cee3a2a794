"""Subprocess helpers for the multi-process store tests."""

from __future__ import annotations

import sys
from multiprocessing.synchronize import Barrier
from typing import Any

from antireplay import ManualClock, ReplayAttackError, ReplayCache
from antireplay.stores import open_store

WALL = 1_800_000_000.0


def race_rounds(spec: str, rounds: int, barrier: Barrier, results: Any) -> None:
    """Each round: wait for the other process, then check the same msg_id once."""
    try:
        clock = ManualClock(wall=WALL)
        store = open_store(spec, clock=ManualClock(wall=WALL - 60))
        cache = ReplayCache(window_s=300, clock=clock, store=store)
        accepted = []
        for i in range(rounds):
            barrier.wait()
            try:
                cache.check(f"round-{i}", WALL - 1)
                accepted.append(i)
            except ReplayAttackError as exc:
                if exc.http_status != 409:
                    raise
        results.put(accepted)
    except BaseException as exc:
        barrier.abort()
        results.put(repr(exc))
        raise


def receive_until_killed(path: str) -> None:
    """Replay every id from the start, then keep receiving new ones; print acceptances."""
    clock = ManualClock(wall=WALL)
    cache = ReplayCache(window_s=300, clock=clock, store=open_store(f"sqlite:{path}"))
    out = sys.stdout
    i = 0
    while True:
        try:
            cache.check(f"m{i}", WALL - 1)
            out.write(f"m{i}\n")
            out.flush()
        except ReplayAttackError:
            pass
        i += 1


if __name__ == "__main__":
    receive_until_killed(sys.argv[1])
