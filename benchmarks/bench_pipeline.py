"""Messages per second through Receiver.receive: fresh signed vs replays, and the SDK baseline.

Run: ``python -m benchmarks.bench_pipeline``.  The replay path must be at least 50x cheaper
than the accept path (it is rejected at step 3, before any cryptography).  Baseline for
verification cost: the official RCAN SDK's own ``verify_message`` (pure-Python ML-DSA-65)
on the same kind of message.
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Iterator
from typing import Any

from cryptography.hazmat.primitives.asymmetric import ed25519, mldsa
from rcan import RCANMessage
from rcan.signing import MLDSAKeyPair, sign_message, verify_message

from antireplay import ManualClock, SecurityConfig
from antireplay.auth import KeyRegistry, sign_envelope
from antireplay.pipeline import Receiver
from benchmarks._timing import per_op_ns, rate

NOW = 1_800_000_000.0


def body(**extra: Any) -> dict[str, Any]:
    return {
        "rcan": "3.2", "rcan_version": "3.2", "msg_id": str(uuid.uuid4()), "timestamp": NOW - 1,
        "cmd": "move_forward", "target": "rcan://registry.rcan.dev/acme/arm/v2/unit-001",
        "params": {"distance_m": 1.0}, **extra,
    }  # fmt: skip


def main() -> None:
    ed, pq = ed25519.Ed25519PrivateKey.generate(), mldsa.MLDSA65PrivateKey.generate()
    keys = KeyRegistry()
    keys.add("ed", "operator", "ed25519", ed.public_key())
    keys.add("pq", "operator", "ml-dsa-65", pq.public_key())
    rx = Receiver(SecurityConfig(msg_id_cache_size=1_000_000), keys, None, None, ManualClock(NOW))
    rows = []
    for kid, key, alg, n in (("ed", ed, "ed25519", 2_000), ("pq", pq, "ml-dsa-65", 1_000)):
        fresh = iter(
            [json.dumps(sign_envelope(body(), kid, alg, key)).encode() for _ in range(n * 7)]
        )

        def accept(it: Iterator[bytes] = fresh) -> object:
            return rx.receive(next(it))

        accept_ns = per_op_ns(accept, n)
        replay = json.dumps(sign_envelope(body(), kid, alg, key)).encode()
        rx.receive(replay)

        def again(raw: bytes = replay) -> object:
            return rx.receive(raw)

        replay_ns = per_op_ns(again, 20_000)
        # The same message re-serialized (other bytes): the full parse + window path.
        other_bytes = json.dumps(json.loads(replay), indent=1).encode()

        def reserialized(raw: bytes = other_bytes) -> object:
            return rx.receive(raw)

        full_ns = per_op_ns(reserialized, 20_000)
        rows += [
            (f"{alg}: accept fresh", accept_ns),
            (f"{alg}: reject exact replay", replay_ns),
            (f"{alg}: reject re-serialized replay", full_ns),
        ]
        print(f"{alg}: re-serialized replay is {accept_ns / full_ns:.0f}x cheaper than accept")
        print(f"{alg}: replay path is {accept_ns / replay_ns:.0f}x cheaper than accept (>= 50x)")
    pair = MLDSAKeyPair.generate()
    msg = RCANMessage(
        cmd="move_forward",
        target="rcan://registry.rcan.dev/acme/arm/v2/unit-001",
        params={"distance_m": 1.0},
    )
    sign_message(msg, pair)
    public = MLDSAKeyPair.from_public_bytes(pair.public_key)
    rows.append(
        (
            "rcan SDK verify_message (baseline)",
            per_op_ns(lambda: verify_message(msg, [public]), 20, 5),
        )
    )
    for name, ns in rows:
        print(f"{name:<40} {ns:>12,.0f} ns {rate(ns)}")
    ours = dict(rows)["ml-dsa-65: accept fresh"]
    print(f"our ML-DSA-65 accept vs SDK verify alone: {rows[-1][1] / ours:.0f}x faster")


if __name__ == "__main__":
    main()
