"""Subprocess helpers for the multi-process store tests."""

from __future__ import annotations

import sys
from multiprocessing.synchronize import Barrier
from typing import Any

from antireplay import ManualClock, ReplayAttackError, ReplayCache, SecurityConfig
from antireplay.rcan.auth import KeyRegistry, load_public_key
from antireplay.rcan.receive import Receiver
from antireplay.state import open_store
from antireplay.state.redis import RedisStore

WALL = 1_800_000_000.0


def race_rounds(
    spec: str, messages: list[bytes], public_pem: bytes, barrier: Barrier, results: Any
) -> None:
    """Each round: wait for the other process, then receive the same signed message once."""
    try:
        keys = KeyRegistry()
        keys.add("op", "operator", "ed25519", load_public_key(public_pem))
        store = open_store(spec, clock=ManualClock(wall=WALL - 400))
        if isinstance(store, RedisStore):
            store.verify()  # first contact of a new deployment: its fence lies in the past
        config = SecurityConfig(replay_window_s=300)
        receiver = Receiver(config, keys, store, None, ManualClock(wall=WALL))
        accepted = []
        for i, raw in enumerate(messages):
            barrier.wait()
            outcome = receiver.receive(raw)
            if outcome.accepted:
                accepted.append(i)
            elif outcome.code != "REPLAY_DETECTED":
                raise AssertionError(f"round {i}: {outcome.code} {outcome.reason}")
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
            cache.commit(f"m{i}", WALL - 1)
            out.write(f"m{i}\n")
            out.flush()
        except ReplayAttackError:
            pass
        i += 1


if __name__ == "__main__":
    receive_until_killed(sys.argv[1])
