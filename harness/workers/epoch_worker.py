"""Subprocess for the kill -9 tests: emit epochs with a frozen wall clock until killed.

The clock never moves, so only the persisted ceiling keeps epochs increasing across restarts.
"""

from __future__ import annotations

import sys

from antireplay import ManualClock
from antireplay.epochs import EpochSigner, signer_state
from harness.workers import emit_forever


def main() -> None:
    signer = EpochSigner(
        b"k" * 32,
        service_name="svc",
        state=signer_state(sys.argv[1]),
        clock=ManualClock(wall=1_000.0),
        reserve_s=float(sys.argv[2]),
    )
    emit_forever(signer.next_epoch)


if __name__ == "__main__":
    main()
