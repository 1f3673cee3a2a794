"""The MAVLink proxy as users run it, beside a direct link, and the guard's per-frame cost.

Run: ``python -m benchmarks.bench_mavlink``.

1. **Link**: ``antireplay mavlink-proxy`` in its own process with its default store
   (SQLite on disk under a temporary directory) and default audit log, fed signed
   ATTITUDE frames from a pymavlink sender at 50, 200 and 1,000 Hz, beside a *direct
   link* (a plain UDP relay process: receive, send, nothing else).  Printed per rate:
   frames dropped and the p50/p99 one-way latency of each path, and what the proxy
   adds.  Targets (issue 14): 0 dropped at 1,000 Hz, added p99 <= 2 ms.
2. **Guard**: frames per second through ``MavlinkGuard.check`` beside pymavlink
   2.4.x ``MAVLink.parse_char`` with signing on, on the same signed frames.
"""

from __future__ import annotations

import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as dialect
from tests.harness import free_port

from antireplay import ManualClock
from antireplay.clock import SystemClock
from antireplay.errors import CounterReplayedError
from antireplay.mavlink import MavlinkGuard, mav_time
from benchmarks._timing import per_op_ns, rate, rejected

KEY = bytes(range(32))
N = 5_000
RATES = (50, 200, 1_000)
SECONDS = 3.0
RELAY = """
import socket, sys
listen, forward = int(sys.argv[1]), int(sys.argv[2])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(("127.0.0.1", listen))
print("relay", flush=True)
while True:
    s.sendto(s.recv(65535), ("127.0.0.1", forward))
"""


class _Sink:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


class _Udp:
    def __init__(self, to: tuple[str, int]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.to = to

    def write(self, data: bytes) -> None:
        self.sock.sendto(data, self.to)


def frames(n: int, start: int) -> list[bytes]:
    sink = _Sink()
    mav = dialect.MAVLink(sink, srcSystem=255, srcComponent=190)
    mav.signing.secret_key, mav.signing.sign_outgoing = KEY, True
    mav.signing.link_id, mav.signing.timestamp = 1, start
    for i in range(n):
        mav.command_long_send(1, 1, 400, 0, float(i), 0, 0, 0, 0, 0, 0)
    return sink.frames


def drive(port: int, vehicle: socket.socket, hz: int) -> tuple[int, list[float]]:
    """Send ``hz * SECONDS`` signed ATTITUDE frames; (dropped, one-way latencies in ms)."""
    count = int(hz * SECONDS)
    sent: dict[int, float] = {}
    got: dict[int, float] = {}

    def receive() -> None:
        vehicle.settimeout(1.0)
        while len(got) < count:
            try:
                data = vehicle.recv(65_535)
            except TimeoutError:
                return
            got[int.from_bytes(data[10:14], "little")] = time.perf_counter()

    receiver = threading.Thread(target=receive)
    receiver.start()
    out = _Udp(("127.0.0.1", port))
    mav = dialect.MAVLink(out, srcSystem=255, srcComponent=190)
    mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id = KEY, True, 1
    wall, start = SystemClock(), time.perf_counter()
    for i in range(1, count + 1):
        delay = start + i / hz - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        mav.signing.timestamp = max(mav.signing.timestamp, mav_time(wall))  # wall-anchored
        sent[i] = time.perf_counter()
        mav.attitude_send(i, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0)
    receiver.join()
    out.sock.close()
    return count - len(got), [(got[i] - sent[i]) * 1e3 for i in got]


def pct(values: list[float], q: int) -> float:
    return statistics.quantiles(values, n=100)[q - 1] if len(values) > 1 else float("nan")


def start(args: list[str], cwd: Path, ready: bytes) -> subprocess.Popen[bytes]:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1] / "src"))
    proc = subprocess.Popen(args, cwd=cwd, env=env, stdout=subprocess.PIPE)
    assert proc.stdout is not None
    if ready not in proc.stdout.readline():
        raise SystemExit(f"{args[:4]} did not start")
    return proc


def link_rows() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        cwd = Path(tmp)
        (cwd / "key.hex").write_text(KEY.hex())
        vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        vehicle.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        vehicle.bind(("127.0.0.1", 0))
        vport = vehicle.getsockname()[1]
        relay_port, proxy_port = free_port(), free_port()
        relay = start([sys.executable, "-c", RELAY, str(relay_port), str(vport)], cwd, b"relay")
        proxy = start(
            [
                sys.executable, "-m", "antireplay", "mavlink-proxy",
                "--listen", f"udp:127.0.0.1:{proxy_port}", "--forward", f"udp:127.0.0.1:{vport}",
                "--key-file", "key.hex", "--system-id", "1",
            ],  # default --store (SQLite on disk) and --audit
            cwd,
            b"mavlink-proxy",
        )  # fmt: skip
        print(f"{'link':<44} {'Hz':>6} {'dropped':>8} {'p50 ms':>8} {'p99 ms':>8}")
        try:
            for hz in RATES:
                direct_drop, direct = drive(relay_port, vehicle, hz)
                proxy_drop, proxied = drive(proxy_port, vehicle, hz)
                for name, dropped, lat in (
                    ("direct link (plain UDP relay process)", direct_drop, direct),
                    ("mavlink-proxy, default SQLite store", proxy_drop, proxied),
                ):
                    print(
                        f"{name:<44} {hz:>6} {dropped:>8} {pct(lat, 50):>8.3f} {pct(lat, 99):>8.3f}"
                    )
                added50 = pct(proxied, 50) - pct(direct, 50)
                added99 = pct(proxied, 99) - pct(direct, 99)
                print(
                    f"{'  added by the proxy':<44} {hz:>6} {'':>8} {added50:>8.3f} {added99:>8.3f}"
                )
        finally:
            for proc in (proxy, relay):
                proc.terminate()
                proc.wait()
            vehicle.close()


def guard_rows() -> None:
    clock = ManualClock(wall=time.time())
    batch = frames(N * 7, mav_time(clock))
    guard = MavlinkGuard(KEY, clock=clock, system_id=1)
    it = iter(batch)
    accept_ns = per_op_ns(lambda: guard.open(next(it)), N)
    replayed = batch[0]

    replay_ns = per_op_ns(rejected(lambda: guard.open(replayed), CounterReplayedError), N)
    receiver = dialect.MAVLink(_Sink(), srcSystem=1, srcComponent=1)
    receiver.signing.secret_key = KEY
    receiver.signing.timestamp = mav_time(clock)
    again = iter(batch)
    base_ns = per_op_ns(lambda: receiver.parse_char(next(again)), N)
    stale = batch[0]
    base_replay_ns = per_op_ns(rejected(lambda: receiver.parse_char(stale), dialect.MAVError), N)
    rows = [
        ("MavlinkGuard.check accept", accept_ns),
        ("MavlinkGuard.check replay", replay_ns),
        ("pymavlink parse_char+decode, signed (baseline)", base_ns),
        ("pymavlink parse_char replay (baseline)", base_replay_ns),
    ]
    for name, ns in rows:
        print(f"{name:<48} {ns:>10,.0f} ns {rate(ns)}")
    print(f"guard accept vs pymavlink: {base_ns / accept_ns:.2f}x the throughput")


def main() -> None:
    link_rows()
    guard_rows()


if __name__ == "__main__":
    main()
