"""Messages per second through Receiver.receive: fresh signed vs replays, and the SDK baseline.

Run: ``python -m benchmarks pipeline``.  The Receiver is wired as the gateway's default
config wires it (:func:`antireplay.wiring.embedded_default`): replay state in SQLite on
disk (WAL, synchronous commits) and the audit log beside it, in a temporary directory.
A replay is rejected by the check before any cryptography (it reads the store and
records nothing), but every rejection is audited, and an audit append is a synchronous
SQLite write: so the same receiver without an audit log runs too, to show what the
check itself costs beside the accept path (signature check plus durable commit).
Baseline for verification cost: the official RCAN SDK's own ``verify_message``
(pure-Python ML-DSA-65) on the same kind of message.
"""

from __future__ import annotations

import json
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from cryptography.hazmat.primitives.asymmetric import ed25519, mldsa
from rcan import RCANMessage
from rcan.signing import MLDSAKeyPair, sign_message, verify_message

from antireplay import ManualClock
from antireplay.audit import AuditLog
from antireplay.core.errors import Code
from antireplay.rcan.auth import KeyRegistry, sign_envelope
from antireplay.rcan.receive import Receiver
from antireplay.state import open_store
from antireplay.wiring import embedded_default
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
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for audited in (True, False):
            config = embedded_default(Path(tmp, "audited" if audited else "bare"))
            clock = ManualClock(NOW - 600)  # the store opens before the rows' messages: a
            store = open_store(  # new state fences its first start, as a memory store does
                config.store,
                clock=clock,
                max_entries=config.security.msg_id_cache_size,
                skew_s=config.security.skew_s,
            )
            clock.advance(600)
            audit = AuditLog(config.audit) if audited else None
            label = "default config" if audited else "same, no audit"
            print(f"{label}: store {config.store.replace(tmp, '$TMP')}, audit {audit is not None}")
            rows += receiver_rows(
                label, Receiver(config.security, keys, store, audit, clock), ed, pq
            )
            store.close()
    rows.append(("rcan SDK verify_message (baseline)", sdk_verify_ns()))
    for name, ns in rows:
        print(f"{name:<56} {ns:>12,.0f} ns {rate(ns)}")
    ours = dict(rows)["default config, ml-dsa-65: accept fresh"]
    print(f"our ML-DSA-65 accept (default config) vs SDK verify: {rows[-1][1] / ours:.1f}x faster")


def receiver_rows(
    label: str, rx: Receiver, ed: ed25519.Ed25519PrivateKey, pq: mldsa.MLDSA65PrivateKey
) -> list[tuple[str, float]]:
    """Accept, exact replay and re-serialized replay through ``rx``, per signature algorithm."""
    rows = []
    for kid, key, alg, n in (("ed", ed, "ed25519", 100), ("pq", pq, "ml-dsa-65", 100)):
        fresh = iter(
            [json.dumps(sign_envelope(body(), kid, alg, key)).encode() for _ in range(n * 7 + 1)]
        )

        def accept(it: Iterator[bytes] = fresh) -> object:
            return rx.receive(next(it))

        accept_ns = per_op_ns(accept, n)
        assert rx.receive(next(fresh)).accepted
        replay = json.dumps(sign_envelope(body(), kid, alg, key)).encode()
        rx.receive(replay)

        def again(raw: bytes = replay) -> object:
            return rx.receive(raw)

        replay_ns = per_op_ns(again, 1_000)
        # The same message re-serialized (other bytes): the full parse + window path.
        other_bytes = json.dumps(json.loads(replay), indent=1).encode()

        def reserialized(raw: bytes = other_bytes) -> object:
            return rx.receive(raw)

        full_ns = per_op_ns(reserialized, 1_000)
        rows += [
            (f"{label}, {alg}: accept fresh", accept_ns),
            (f"{label}, {alg}: reject exact replay", replay_ns),
            (f"{label}, {alg}: reject re-serialized replay", full_ns),
        ]
        assert rx.receive(replay).code == rx.receive(other_bytes).code == Code.REPLAY_DETECTED
        print(f"{label}, {alg}: accept / re-serialized replay: {accept_ns / full_ns:.1f}x")
        print(f"{label}, {alg}: accept / exact replay: {accept_ns / replay_ns:.1f}x")
    return rows


def sdk_verify_ns() -> float:
    pair = MLDSAKeyPair.generate()
    msg = RCANMessage(
        cmd="move_forward",
        target="rcan://registry.rcan.dev/acme/arm/v2/unit-001",
        params={"distance_m": 1.0},
    )
    sign_message(msg, pair)
    public = MLDSAKeyPair.from_public_bytes(pair.public_key)
    return per_op_ns(lambda: verify_message(msg, [public]), 20, 5)


if __name__ == "__main__":
    main()
