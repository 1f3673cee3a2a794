"""Epoch announcements: seal/open rates and the cost of persistence per announcement.

Run: ``python -m benchmarks.bench_epochs``.  Baseline for persistence: an fsync per epoch
(``reserve_s=0``: every epoch is above the ceiling), side by side with block reservation.
The verifier persists through the replay store contract (one ``advance`` per accepted
announcement on a ``sqlite:`` store).  Verifiers are built on a clock that started two
minutes ago, so their restart fence is behind the epochs they open.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from antireplay.core.clock import ManualClock
from antireplay.epochs import EpochSigner, EpochVerifier, signer_state
from antireplay.state import open_store
from benchmarks._timing import per_op_ns, rate

PSK = b"bench-pre-shared-key-0123456789abcdef"
PAYLOAD = b"participant guid=0102030405060708 locators=udpv4://10.0.0.5:7400 " * 3


def _started_earlier(spec: str | None = None) -> EpochVerifier:
    """A verifier whose store (and restart fence) began two minutes ago."""
    clock = ManualClock(wall=time.time() - 120)
    store = None if spec is None else open_store(spec, clock=clock)
    verifier = EpochVerifier(PSK, store=store, clock=clock)
    clock.step_wall(120)
    return verifier


def main() -> None:
    signer, verifier = EpochSigner(PSK), _started_earlier()
    rows = [("seal (memory)", per_op_ns(lambda: signer.seal(PAYLOAD), 20_000))]
    sealed = iter([signer.seal(PAYLOAD) for _ in range(7 * 20_000)])
    rows.append(("open (memory)", per_op_ns(lambda: verifier.open(next(sealed)), 20_000)))
    with tempfile.TemporaryDirectory() as tmp:
        block = EpochSigner(PSK, state=signer_state(Path(tmp) / "block"), reserve_s=1.0)
        per_epoch = EpochSigner(PSK, state=signer_state(Path(tmp) / "each"), reserve_s=0.0)
        block_ns = per_op_ns(lambda: block.seal(PAYLOAD), 5_000)
        each_ns = per_op_ns(lambda: per_epoch.seal(PAYLOAD), 50, repeats=5)
        rows.append(("seal + block reservation (1 s)", block_ns))
        rows.append(("seal + fsync per epoch (baseline)", each_ns))
        durable_verifier = _started_earlier(f"sqlite:{Path(tmp) / 'verifier.db'}")
        more = iter([signer.seal(PAYLOAD) for _ in range(5 * 50)])
        rows.append(
            (
                "open + persist (verifier, sqlite advance)",
                per_op_ns(lambda: durable_verifier.open(next(more)), 50, 5),
            )
        )
    for name, ns in rows:
        print(f"{name:<36} {ns:>12,.0f} ns {rate(ns)}")
    print(f"block reservation is {each_ns / block_ns:.0f}x cheaper than fsync per epoch")


if __name__ == "__main__":
    main()
