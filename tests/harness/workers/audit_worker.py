"""Subprocess for the kill -9 rotation tests: append audit rows one by one, print each
acknowledged sequence number, and stop dead at a chosen step of a chosen rotation.

``argv``: trail path, the step (``sealed``, ``prepared``, ``published``, ``retaining``), the
rotation (or retention) to stop in.  The writer thread blocks there, holding the lock,
until the test kills the process: every row acknowledged so far was printed first.
"""

from __future__ import annotations

import sys
import threading
from pathlib import Path

from antireplay.audit import AuditLog, Retention
from tests.harness.audit import SMALL_SEGMENT, append


class StoppingLog(AuditLog):
    """An audit writer that announces ``STOP <step>`` and hangs at the chosen point."""

    def __init__(self, path: Path, step: str, nth: int) -> None:
        self.step, self.nth, self.seen = step, nth, 0
        budget = Retention(segment_bytes=SMALL_SEGMENT, max_bytes=3 * SMALL_SEGMENT + 8192)
        super().__init__(path, retention=budget)

    def _rotation_point(self, step: str) -> None:
        if step != self.step:
            return
        self.seen += 1
        if self.seen == self.nth:
            sys.stdout.write(f"STOP {step}\n")
            sys.stdout.flush()
            threading.Event().wait()  # killed here


def main() -> None:
    log = StoppingLog(Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]))
    for i in range(1_000_000):
        seq = append(log, i)
        sys.stdout.write(f"{seq}\n")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
