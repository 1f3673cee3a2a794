"""The MAVLink router as users run it, beside a direct link and MAVProxy, and the guard's cost.

Run: ``python -m benchmarks.bench_mavlink``.

1. **Latency**: signed ATTITUDE frames from a pymavlink sender at 50, 200 and 1,000 Hz
   through four paths to one receiver: a *direct link* (a plain UDP relay process:
   receive, send, nothing else); ``antireplay mavlink-router`` in its own process with
   its default store (SQLite on disk) and audit log, verifying on a ground endpoint;
   the same router *signing on behalf* of a tool that sends unsigned frames to its
   trusted endpoint; and MAVProxy (from PyPI, headless) forwarding the same frames from
   its master to its ``--out``, signing on with the same passphrase key (it verifies
   what it forwards).  Printed per rate: frames dropped, p50/p99 one-way latency, and
   what each adds over the direct link.  Targets (issue 14): 0 dropped at 1,000 Hz,
   added p99 <= 2 ms.
2. **Throughput**: a burst of ``BURST`` frames through each path, built beforehand and
   signed just then, sent as fast as the path takes them with ``WINDOW`` in flight (one
   thread sends and counts: the sender is not the limit, no queue overflows), each
   ground station one socket for the run; frames delivered, delivered frames per second
   and the forwarder's CPU per frame (``/proc``: robust on a shared box), medians of
   ``--rounds`` rounds.  Goals (issue 38): verifying >= 2.5x MAVProxy, signing on
   behalf >= 1.5x; a frame not forwarded makes the row a FAIL, never a ratio.
   ``--rows latency,burst,guard`` picks the parts.
3. **Guard**: frames per second through ``MavlinkGuard.open`` beside pymavlink
   2.4.x ``MAVLink.parse_char`` with signing on, on the same signed frames.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.core.clock import ManualClock, SystemClock
from antireplay.core.errors import CounterReplayedError
from antireplay.mavlink import MavlinkGuard, mav_time, passphrase_key
from antireplay.state.sqlite import SqliteStore
from benchmarks._timing import per_op_ns, rate, rejected
from harness import free_port

PASSPHRASE = "bench-passphrase"
KEY = passphrase_key(PASSPHRASE)
N = 5_000
BURST = 5_000
RATES = (50, 200, 1_000)
SECONDS = 3.0
WINDOW = 64  # frames in flight in a burst: well below a forwarder's UDP receive queue
LOST_S = 0.25  # a burst's frame not arrived after this is lost
ROUNDS = 3
DIRECT = "direct link (plain UDP relay process)"
#: The ground station signs as 255/190; the unsigned tool on the trusted endpoint is another
#: system (the router binds a station's authenticated system to its link while it is live,
#: so a trusted link claiming 255 within seconds of the signed burst would be SOURCE_BOUND).
GCS, TOOL = (255, 190), (254, 190)
VERIFYING = "mavlink-router, verifying (SQLite store)"
BEHALF = "mavlink-router, signing on behalf"
MAVPROXY = "MAVProxy 1.8 forwarding, signing on"
#: Issue 38: a burst through the router against MAVProxy forwarding with signing.
GOALS = {VERIFYING: 2.5, BEHALF: 1.5}
RELAY = """
import socket, sys
listen, forward = int(sys.argv[1]), int(sys.argv[2])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); s.bind(("127.0.0.1", listen))
print("relay", flush=True)
while True:
    s.sendto(s.recv(65535), ("127.0.0.1", forward))
"""


Launch = Callable[[], subprocess.Popen[bytes]]


class _Sink:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


_SENDERS: dict[int, socket.socket] = {}


def sender(port: int) -> socket.socket:
    """The one socket that sends to ``port`` for the whole run, as a ground station has one
    (a new source port per round would leave the router a dead peer to send to each time)."""
    if port not in _SENDERS:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", 0))  # not connected: a path still starting refuses nothing
        _SENDERS[port] = sock
    return _SENDERS[port]


class _Udp:
    def __init__(self, port: int) -> None:
        self.sock, self.to = sender(port), ("127.0.0.1", port)

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


def attitudes(count: int, signed: bool) -> list[bytes]:
    """``count`` ATTITUDE frames numbered 1.., signed now (fresh whatever the run length)."""
    sink = _Sink()
    sysid, compid = GCS if signed else TOOL
    mav = dialect.MAVLink(sink, srcSystem=sysid, srcComponent=compid)
    if signed:
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id = KEY, True, 1
        mav.signing.timestamp = mav_time(SystemClock())
    for i in range(1, count + 1):
        mav.attitude_send(i, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0)
    return sink.frames


def burst(port: int, vehicle: socket.socket, count: int, signed: bool = True) -> tuple[int, float]:
    """Send ``count`` frames built beforehand (signed just now) as fast as the path takes
    them, at most ``WINDOW`` in flight, from one thread that also counts what arrives (the
    sender is never the limit, and no queue overflows); (frames delivered, delivered frames
    per second).  A frame lost costs ``LOST_S`` of waiting and is counted."""
    batch = attitudes(count, signed)
    out, to = sender(port), ("127.0.0.1", port)
    vehicle.settimeout(LOST_S)
    got: set[int] = set()
    sent, waiting, start = 0, 0, time.perf_counter()
    last = start
    while len(got) < count:
        if sent < count and waiting < WINDOW:
            out.sendto(batch[sent], to)
            sent, waiting = sent + 1, waiting + 1
            continue
        try:
            data = vehicle.recv(65_535)
        except TimeoutError:
            if sent == count:
                break
            waiting = 0  # lost on the way: let the sender go on
            continue
        if data[7:10] == b"\x1e\x00\x00":  # ATTITUDE; a forwarder may add its own frames
            got.add(int.from_bytes(data[10:14], "little"))
            waiting, last = max(waiting - 1, 0), time.perf_counter()
    return len(got), len(got) / (last - start) if last > start else 0.0


def drive(
    port: int, vehicle: socket.socket, hz: float, count: int, signed: bool = True
) -> tuple[int, list[float], float]:
    """Send ``count`` ATTITUDE frames at ``hz`` (``inf``: a :func:`burst`, no latencies),
    signed or not; (dropped, one-way latencies in ms, delivered frames per second)."""
    if hz == float("inf"):
        delivered, per_s = burst(port, vehicle, count, signed)
        return count - delivered, [], per_s
    sent: dict[int, float] = {}
    got: dict[int, float] = {}

    def receive() -> None:
        vehicle.settimeout(1.0)
        while len(got) < count:
            try:
                data = vehicle.recv(65_535)
            except TimeoutError:
                return
            if data[7:10] == b"\x1e\x00\x00":  # ATTITUDE; a forwarder may add its own frames
                got[int.from_bytes(data[10:14], "little")] = time.perf_counter()

    receiver = threading.Thread(target=receive)
    receiver.start()
    out = _Udp(port)
    sysid, compid = GCS if signed else TOOL
    mav = dialect.MAVLink(out, srcSystem=sysid, srcComponent=compid)
    if signed:
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
    span = max(got.values(), default=start) - start
    return (
        count - len(got),
        [(got[i] - sent[i]) * 1e3 for i in got],
        len(got) / span if span else 0.0,
    )


def pct(values: list[float], q: int) -> float:
    return statistics.quantiles(values, n=100)[q - 1] if len(values) > 1 else float("nan")


def start(
    args: list[str], cwd: Path, ready: bytes | None, home: Path | None = None
) -> subprocess.Popen[bytes]:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1] / "src"))
    if home is not None:
        env["HOME"] = str(home)
    proc = subprocess.Popen(
        args, cwd=cwd, env=env, stdout=subprocess.PIPE, stdin=subprocess.DEVNULL
    )
    assert proc.stdout is not None
    if ready is not None and ready not in proc.stdout.readline():
        raise SystemExit(f"{args[:4]} did not start")
    return proc


def mavproxy(cwd: Path, master_port: int, vport: int) -> subprocess.Popen[bytes]:
    """MAVProxy forwarding its master (signed with the passphrase key) to ``vport``."""
    script = Path(sys.executable).parent / "mavproxy.py"
    if not script.exists():
        raise SystemExit("MAVProxy is not installed: pip install -e '.[dev]'")
    master = f"udpin:127.0.0.1:{master_port}"
    (cwd / ".mavproxy").mkdir(exist_ok=True)
    (cwd / ".mavproxy" / "signing.keys").write_text(f"{master} {PASSPHRASE}\n")
    args = [
        sys.executable, str(script), "--master", master, "--out", f"udpout:127.0.0.1:{vport}",
        "--daemon", "--non-interactive", "--no-state", "--default-modules", "signing",
    ]  # fmt: skip
    return start(args, cwd, None, home=cwd)


def warm(port: int, vehicle: socket.socket, signed: bool) -> None:
    """Send until the path delivers (MAVProxy takes seconds to start; a polled deadline)."""
    deadline = time.monotonic() + 60
    while drive(port, vehicle, 50, 10, signed)[0] == 10:
        if time.monotonic() > deadline:
            raise SystemExit(f"nothing came through port {port}")


def seed_router_state(cwd: Path) -> None:
    """The router's default store in ``cwd`` as a deployment started 10 min ago: a new state
    fences the router's first start (``max_forward_s``), which is not what a burst measures."""
    state = cwd / ".antireplay" / "mavlink.db"
    SqliteStore(state, clock=ManualClock(wall=time.time() - 600)).close()


def cpu_s(pid: int) -> float:
    """User + system CPU seconds process ``pid`` has used so far (all its threads)."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Burst(NamedTuple):
    """One path's bursts: frames delivered, delivered frames per second and the
    forwarder's CPU microseconds per frame, one entry per round."""

    got: list[int]
    per_s: list[float]
    cpu_us: list[float]


def router_args(port: int, trusted_port: int, vport: int) -> list[str]:
    """``antireplay mavlink-router`` as a user runs it: a ground and a trusted endpoint,
    the vehicle, the default store (SQLite on disk in its directory) and audit."""
    return [
        sys.executable, "-m", "antireplay", "mavlink-router",
        "--ground", f"udpin:127.0.0.1:{port}", "--trusted", f"udpin:127.0.0.1:{trusted_port}",
        "--vehicle", f"udpout:127.0.0.1:{vport}", "--passphrase-env", "MAV_PASSPHRASE",
        "--system-id", "1",
    ]  # fmt: skip


def link_rows(rows: set[str], rounds: int = ROUNDS) -> dict[str, Burst]:
    """Each forwarder runs alone while it is measured (MAVProxy idling beside the router
    would take CPU from it on a 2-core box); burst rounds alternate the forwarders, each
    started afresh per round.  Returns the bursts by path name."""
    with tempfile.TemporaryDirectory() as tmp:
        cwd = Path(tmp)
        os.environ["MAV_PASSPHRASE"] = PASSPHRASE
        vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        vehicle.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        vehicle.bind(("127.0.0.1", 0))
        vport = vehicle.getsockname()[1]
        port, trusted_port = free_port(), free_port()
        seed_router_state(cwd)
        forwarders: list[tuple[Launch, list[tuple[str, int, bool]]]] = [
            (
                lambda: start([sys.executable, "-c", RELAY, str(port), str(vport)], cwd, b"relay"),
                [(DIRECT, port, True)],
            ),
            (
                lambda: start(router_args(port, trusted_port, vport), cwd, b"mavlink-router"),
                [(VERIFYING, port, True), (BEHALF, trusted_port, False)],
            ),
            (lambda: mavproxy(cwd, port, vport), [(MAVPROXY, port, True)]),
        ]  # fmt: skip
        latency: dict[str, dict[int, tuple[int, list[float]]]] = {}
        bursts: dict[str, Burst] = {}
        try:
            for r in range(rounds if "burst" in rows else 1):
                for launch, paths in forwarders:
                    proc = launch()
                    try:
                        for name, to, signed in paths:
                            warm(to, vehicle, signed)
                            if r == 0 and "latency" in rows:
                                latency[name] = {
                                    hz: drive(to, vehicle, hz, int(hz * SECONDS), signed)[:2]
                                    for hz in RATES
                                }
                            if "burst" in rows:
                                before = cpu_s(proc.pid)
                                got, per_s = burst(to, vehicle, BURST, signed)
                                spent = cpu_s(proc.pid) - before
                                row = bursts.setdefault(name, Burst([], [], []))
                                row.got.append(got)
                                row.per_s.append(per_s)
                                row.cpu_us.append(spent / max(got, 1) * 1e6)
                    finally:
                        proc.terminate()
                        proc.wait()
        finally:
            vehicle.close()
        if latency:
            print_latency(latency)
        if bursts:
            print_bursts(bursts)
        return bursts


def print_latency(latency: dict[str, dict[int, tuple[int, list[float]]]]) -> None:
    print(f"{'latency':<44} {'Hz':>6} {'dropped':>8} {'p50 ms':>8} {'p99 ms':>8}")
    direct = latency[DIRECT]
    for hz in RATES:
        for name, rows in latency.items():
            dropped, lat = rows[hz]
            print(f"{name:<44} {hz:>6} {dropped:>8} {pct(lat, 50):>8.3f} {pct(lat, 99):>8.3f}")
            if rows is not direct:
                base = direct[hz][1]
                added = pct(lat, 50) - pct(base, 50), pct(lat, 99) - pct(base, 99)
                print(f"{'  added':<44} {hz:>6} {'':>8} {added[0]:>8.3f} {added[1]:>8.3f}")


def burst_verdict(name: str, bursts: dict[str, Burst]) -> str:
    """The row's ratio against MAVProxy beside its goal: PASS or MISS, or FAIL where a
    frame of the row or of its baseline was not forwarded (no ratio then)."""
    lost = {n: BURST * len(bursts[n].got) - sum(bursts[n].got) for n in (name, MAVPROXY)}
    if any(lost.values()):
        return "FAIL (" + ", ".join(f"{n}: {k} frames not forwarded" for n, k in lost.items()) + ")"
    ratio = statistics.median(bursts[name].per_s) / statistics.median(bursts[MAVPROXY].per_s)
    cpu = statistics.median(bursts[MAVPROXY].cpu_us) / statistics.median(bursts[name].cpu_us)
    goal = GOALS[name]
    return f"{ratio:.2f}x MAVProxy ({cpu:.2f}x by CPU per frame), goal >= {goal}x: " + (
        "PASS" if ratio >= goal else "MISS"
    )


def print_bursts(bursts: dict[str, Burst]) -> None:
    rounds = len(next(iter(bursts.values())).got)
    print(f"throughput: bursts of {BURST:,} frames, {WINDOW} in flight, medians of {rounds} rounds")
    print(f"{'path':<44} {'got':>9} {'frames/s':>10} {'CPU us/frame':>13}")
    for name, row in bursts.items():
        print(
            f"{name:<44} {min(row.got):>9} {statistics.median(row.per_s):>10,.0f}"
            f" {statistics.median(row.cpu_us):>13.1f}"
        )
    for name in GOALS:
        if name in bursts and MAVPROXY in bursts:
            print(f"{name}: {burst_verdict(name, bursts)}")


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
        ("MavlinkGuard.open accept", accept_ns),
        ("MavlinkGuard.open replay", replay_ns),
        ("pymavlink parse_char+decode, signed (baseline)", base_ns),
        ("pymavlink parse_char replay (baseline)", base_replay_ns),
    ]
    for name, ns in rows:
        print(f"{name:<48} {ns:>10,.0f} ns {rate(ns)}")
    print(f"guard accept vs pymavlink: {base_ns / accept_ns:.2f}x the throughput")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks mavlink")
    parser.add_argument("--rows", default="latency,burst,guard", help="latency, burst, guard")
    parser.add_argument("--rounds", type=int, default=ROUNDS, help="burst rounds")
    opts = parser.parse_args(argv)
    rows = set(opts.rows.split(","))
    print(f"load average {Path('/proc/loadavg').read_text().split(' ', 3)[:3]}", flush=True)
    if rows & {"latency", "burst"}:
        link_rows(rows, opts.rounds)
    if "guard" in rows:
        guard_rows()
    print(f"load average {Path('/proc/loadavg').read_text().split(' ', 3)[:3]}")


if __name__ == "__main__":
    main()
