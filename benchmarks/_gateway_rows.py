"""Helpers of ``bench_gateway``'s rows that are not HTTP load: in-process refusals, the
MAVLink router's burst, and what the gateway under test can do.

* The refusal contenders time a msg_id the full cache already holds: ours through
  ``ReplayCache.try_check``, the receiver's replay check (a :class:`Refusal` value; an
  admission fails the run), rcan's ``check_and_record``.
* The router's burst reuses :mod:`benchmarks.bench_mavlink`'s sender and launchers:
  the router (``antireplay mavlink-router``, its default SQLite store and audit) and
  MAVProxy run one at a time, so neither idles beside the other on a 2-core box.
"""

from __future__ import annotations

import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import httpx
from cryptography.hazmat.primitives.asymmetric import ed25519
from rcan.replay import ReplayCache as RcanCache

from antireplay import ReplayCache
from antireplay.core.errors import ReplayAttackError
from antireplay.core.window import Refusal
from benchmarks import bench_mavlink as mav
from benchmarks import bench_window as window
from benchmarks._gateway_load import JSON, Server, envelope
from benchmarks._timing import Batch
from harness import free_port


def accepting(server: Server, key: ed25519.Ed25519PrivateKey) -> None:
    """Send fresh commands until one is accepted: a store met for the first time may raise
    its fence to now (it cannot tell an empty store from a lost one), refusing anything
    signed before; the measured bodies are signed after this."""
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        answer = httpx.post(server.url + "/v1/messages", content=envelope(key), headers=JSON)
        if answer.status_code == 200:
            return
        time.sleep(0.2)
    raise SystemExit(f"{server.name}: no fresh command accepted in 30 s: {answer.text}")


def memory_refusals(work: window.Workload, size: int, batch: int) -> Batch:
    """``ReplayCache.try_check`` (the receiver's step 3) of a msg_id the full memory store
    holds: refused, as a value."""
    clock = window.StoppedClock(work.t0)
    cache = ReplayCache(window_s=300, max_size=size, clock=clock)
    clock.move_to(work.now)
    for mid, ts in zip(work.fill, work.fill_stamps, strict=True):
        cache.commit(mid, ts)
    seen, stamp = work.fill[-1], work.fill_stamps[-1]
    return lambda _r: refuse_all(cache.try_check, seen, stamp, batch)


def refuse_all(commit: Callable[[str, float], object], seen: str, stamp: float, n: int) -> None:
    for _ in range(n):
        try:
            result = commit(seen, stamp)
        except ReplayAttackError:
            continue
        if not isinstance(result, Refusal):
            raise AssertionError("a replay was accepted")


def rcan_refusals(size: int, batch: int) -> Batch:
    cache = RcanCache(window_s=300, max_size=size)
    now = time.time()
    for mid in window.ids("fill", size):
        cache.check_and_record(mid, now)
    seen = window.ids("fill", size)[-1]

    def run(_r: int) -> None:
        check = cache.check_and_record
        for _ in range(batch):
            if check(seen, now)[0]:
                raise AssertionError("rcan accepted a replay")

    return run


def router_bursts(rounds: int) -> dict[str, float]:
    """Median frames/s of a burst through the router (verifying, on behalf) and MAVProxy."""
    with tempfile.TemporaryDirectory() as tmp:
        cwd = Path(tmp)
        os.environ["MAV_PASSPHRASE"] = mav.PASSPHRASE
        vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        vehicle.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        vehicle.bind(("127.0.0.1", 0))
        vport = vehicle.getsockname()[1]
        port, trusted = free_port(), free_port()
        router = [sys.executable, "-m", "antireplay", "mavlink-router",
                  "--ground", f"udpin:127.0.0.1:{port}", "--trusted", f"udpin:127.0.0.1:{trusted}",
                  "--vehicle", f"udpout:127.0.0.1:{vport}", "--passphrase-env", "MAV_PASSPHRASE",
                  "--system-id", "1"]  # fmt: skip
        mav.seed_router_state(cwd)
        launches: list[tuple[Callable[[], subprocess.Popen[bytes]], list[tuple[str, int, bool]]]]
        launches = [
            (lambda: mav.start(router, cwd, b"mavlink-router"),
             [("verifying", port, True), ("on behalf", trusted, False)]),
            (lambda: mav.mavproxy(cwd, port, vport), [("mavproxy", port, True)]),
        ]  # fmt: skip
        rates: dict[str, list[float]] = {}
        try:
            for launch, paths in launches:
                proc = launch()
                try:
                    for _, to, signed in paths:
                        mav.warm(to, vehicle, signed)
                    for _ in range(rounds):
                        for name, to, signed in paths:
                            per_s = mav.drive(to, vehicle, float("inf"), mav.BURST, signed)[2]
                            rates.setdefault(name, []).append(per_s)
                finally:
                    proc.terminate()
                    proc.wait()
        finally:
            vehicle.close()
    return {name: statistics.median(r) for name, r in rates.items()}


def has_workers() -> bool:
    helptext = subprocess.run(
        [sys.executable, "-m", "antireplay", "serve", "--help"],
        capture_output=True, text=True, check=False,
    ).stdout  # fmt: skip
    return "--workers" in helptext
