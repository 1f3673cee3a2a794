"""Counters and sessions: accept rates, seal/open, ML-DSA-87, and replay-rejection cost.

Run: ``python -m benchmarks.bench_counters``.  The replayed frame is rejected by the
window check *before* any cryptography; its cost is compared with a full verify.
"""

from __future__ import annotations

import itertools

from cryptography.hazmat.primitives.asymmetric import mldsa, mlkem

from antireplay.core.counters import CounterWindow, FencedTable
from antireplay.core.errors import CounterReplayedError
from antireplay.pq.session import Initiator, Purpose, Responder
from benchmarks._timing import per_op_ns, rate, rejected


def main() -> None:
    window, table = CounterWindow(), FencedTable[int, list[int]](1024)
    w_next, t_next = itertools.count(), itertools.count(1)
    rows = [
        ("CounterWindow.commit", per_op_ns(lambda: window.commit(next(w_next)), 50_000)),
        ("FencedTable.commit", per_op_ns(lambda: table.commit(1, next(t_next), list), 50_000)),
    ]
    gcs_key, kem = mldsa.MLDSA87PrivateKey.generate(), mlkem.MLKEM1024PrivateKey.generate()
    gcs = Initiator("gcs", gcs_key)
    robot = Responder(kem, {"gcs": gcs_key.public_key()})
    hs1 = gcs.start(kem.public_key())
    _, hs2 = robot.accept_handshake(hs1)
    gcs_side = gcs.finish(hs1, hs2)
    payload = b"COMMAND_LONG target=1 cmd=400 param1=1" * 2
    rows.append(("session seal (HMAC)", per_op_ns(lambda: gcs_side.seal(payload), 20_000)))
    frames = iter([gcs_side.seal(payload) for _ in range(7 * 20_000)])
    rows.append(("session open (HMAC)", per_op_ns(lambda: robot.open(next(frames)), 20_000)))
    commands = iter([gcs_side.seal(payload, Purpose.COMMAND) for _ in range(7 * 300)])
    verify_ns = per_op_ns(lambda: robot.open(next(commands)), 300)
    message = b"x" * 100
    sig = gcs_key.sign(message)
    pub = gcs_key.public_key()
    rows.append(("ML-DSA-87 sign", per_op_ns(lambda: gcs_key.sign(message), 300)))
    rows.append(("ML-DSA-87 verify", per_op_ns(lambda: pub.verify(sig, message), 300)))
    rows.append(("open signed command (verify)", verify_ns))
    replayed = gcs_side.seal(payload, Purpose.COMMAND)
    robot.open(replayed)

    reject_ns = per_op_ns(rejected(lambda: robot.open(replayed), CounterReplayedError), 20_000)
    rows.append(("reject replayed command", reject_ns))
    for name, ns in rows:
        print(f"{name:<32} {ns:>10,.0f} ns {rate(ns)}")
    print(
        f"replay rejection / full verify: 1/{verify_ns / reject_ns:.0f} "
        f"(must be well under 1/50: rejection happens before crypto)"
    )


if __name__ == "__main__":
    main()
