"""Frames per second through MavlinkGuard.check vs pymavlink's own signed parsing.

Run: ``python -m benchmarks.bench_mavlink``.  Baseline: pymavlink 2.4.x ``MAVLink.parse_char``
(which decodes and checks the signature and stream timestamp) with signing enabled, on the
same signed COMMAND_LONG frames, side by side.
"""

from __future__ import annotations

import time

from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay import ManualClock
from antireplay.errors import CounterReplayError
from antireplay.mavlink import MavlinkGuard, mav_time
from benchmarks._timing import per_op_ns, rate, rejected

KEY = bytes(range(32))
N = 5_000


class _Sink:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


def frames(n: int, start: int) -> list[bytes]:
    sink = _Sink()
    mav = dialect.MAVLink(sink, srcSystem=255, srcComponent=190)
    mav.signing.secret_key, mav.signing.sign_outgoing = KEY, True
    mav.signing.link_id, mav.signing.timestamp = 1, start
    for i in range(n):
        mav.command_long_send(1, 1, 400, 0, float(i), 0, 0, 0, 0, 0, 0)
    return sink.frames


def main() -> None:
    clock = ManualClock(wall=time.time())
    batch = frames(N * 7, mav_time(clock))
    guard = MavlinkGuard(KEY, clock=clock, system_id=1)
    it = iter(batch)
    accept_ns = per_op_ns(lambda: guard.check(next(it)), N)
    replayed = batch[0]

    replay_ns = per_op_ns(rejected(lambda: guard.check(replayed), CounterReplayError), N)
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


if __name__ == "__main__":
    main()
