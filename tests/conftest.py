"""Shared fixtures and helpers."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import pytest

from antireplay import ManualClock, ReplayAttackError, ReplayCache, SecurityConfig
from antireplay.audit import AuditLog
from antireplay.rcan.receive import Receiver
from tests.envelopes import NOW, registry
from tests.redis_server import RedisServer

ROOT = Path(__file__).resolve().parent.parent
T = TypeVar("T")


def _fresh_cache(*args: Any, **kwargs: Any) -> ReplayCache:
    """A ReplayCache whose ManualClock is moved past its restart fence (start + skew + window).

    A new in-memory cache refuses anything stamped at or before its start plus skew
    (it cannot know what a previous process accepted); tests that are not about
    that fence start just after it.
    """
    cache = ReplayCache(*args, **kwargs)
    clock = kwargs.get("clock", args[3] if len(args) > 3 else None)
    if isinstance(clock, ManualClock):
        clock.advance(cache.policy.window_s + cache.policy.skew_s + 1)
    return cache


#: How long before a test's "now" its receiver's in-memory store started (> window + skew).
STARTED_BEFORE_S = 400.0


def fresh_receiver(*args: Any, **kwargs: Any) -> Receiver:
    """A Receiver whose in-memory store started long enough ago that its restart fence
    refuses nothing the test sends (the fence has its own tests)."""
    clock = kwargs.get("clock", args[4] if len(args) > 4 else None)
    if not isinstance(clock, ManualClock):
        return Receiver(*args, **kwargs)
    clock.step_wall(-STARTED_BEFORE_S)
    try:
        return Receiver(*args, **kwargs)
    finally:
        clock.step_wall(STARTED_BEFORE_S)


def started_before(clock: ManualClock, build: Callable[[], T]) -> T:
    """``build()`` on ``clock`` stepped ``STARTED_BEFORE_S`` back: an epoch verifier or DDS
    reader whose in-memory store (and start fence) began long before the test's "now"
    (the fence has its own tests)."""
    clock.step_wall(-STARTED_BEFORE_S)
    try:
        return build()
    finally:
        clock.step_wall(STARTED_BEFORE_S)


@pytest.fixture
def impl() -> Callable[..., ReplayCache]:
    """Builds caches as tests need them.  The compiled build runs here; the pure-Python
    build runs the same tests in a subprocess (tests/core/test_native.py)."""
    return _fresh_cache


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(wall=NOW)


@pytest.fixture
def receiver(tmp_path: Path, clock: ManualClock) -> Receiver:
    """A Receiver trusting :func:`tests.envelopes.registry`, auditing to ``tmp_path``."""
    return fresh_receiver(
        SecurityConfig(), registry(), None, AuditLog(tmp_path / "audit.db"), clock
    )


def run_threads(threads_n: int, work: Callable[[int], object]) -> None:
    """Run ``work(index)`` in ``threads_n`` real threads released together by a barrier."""
    barrier = threading.Barrier(threads_n)

    def worker(index: int) -> None:
        barrier.wait()
        work(index)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(threads_n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def race(threads_n: int, action: Callable[[], object]) -> tuple[int, int]:
    """Start ``threads_n`` threads behind a barrier; count successes and typed rejections."""
    results: list[bool] = []
    lock = threading.Lock()

    def attempt(_: int) -> None:
        try:
            action()
            ok = True
        except ReplayAttackError:
            ok = False
        with lock:
            results.append(ok)

    run_threads(threads_n, attempt)
    return results.count(True), results.count(False)


def run_and_kill(args: list[str], lines: int, rng: random.Random) -> list[str]:
    """Start a Python helper, read ``lines`` lines of output, then SIGKILL it mid-stride."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT / "src"), str(ROOT)]))
    proc = subprocess.Popen(
        [sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True
    )
    assert proc.stdout is not None
    out: list[str] = []
    for _ in range(lines):
        line = proc.stdout.readline()
        if not line:
            break
        out.append(line.strip())
    if rng.random() < 0.5:  # sometimes let it run a little further before the kill
        for _ in range(rng.randint(1, 50)):
            line = proc.stdout.readline()
            if line:
                out.append(line.strip())
    proc.send_signal(signal.SIGKILL)
    rest, err = proc.communicate(timeout=30)
    out.extend(x for x in rest.split("\n") if x.strip())
    if proc.returncode != -signal.SIGKILL:
        raise AssertionError(f"helper exited {proc.returncode}: {err}")
    return out


@pytest.fixture(scope="session")
def redis_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A real redis-server started for this test session (fails, never skips, if missing)."""
    server = RedisServer(tmp_path_factory.mktemp("redis"))
    server.start()
    try:
        yield server.url
    finally:
        server.stop()


def kill9_runs(args: list[str], rounds: int, max_lines: int, seed: int) -> list[list[str]]:
    """Run a helper ``rounds`` times on the same state, SIGKILLing each at a random moment."""
    rng = random.Random(seed)
    return [run_and_kill(args, rng.randint(1, max_lines), rng) for _ in range(rounds)]


def assert_never_reused(runs: list[list[str]], what: str) -> None:
    """Each run starts above everything earlier runs printed, and no value ever repeats."""
    seen: list[int] = []
    for lines in runs:
        values = [int(x) for x in lines]
        assert values, "worker produced nothing"
        if seen:
            assert values[0] > max(seen), f"a restarted {what} reused a value"
        seen.extend(values)
    assert len(seen) == len(set(seen))
