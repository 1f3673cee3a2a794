"""Subprocess for the audit rotation tests: append audit rows one by one, print each
acknowledged sequence number, and stop dead at a chosen step of a chosen rotation.

``argv``: trail path, the step (``sealed``, ``prepared``, ``published``, ``retaining``), the
rotation (or retention) to stop in.  The writer thread blocks there, holding the lock,
until the test kills the process: every row acknowledged so far was printed first.
With the step ``append``: one of several writers on one trail, appending ``argv[3]`` rows
``<argv[4]>-<i>`` under :data:`BUDGET`, printing each acknowledged ``msg_id``
(:func:`concurrent`).
"""

from __future__ import annotations

import sys
import threading
from pathlib import Path

from antireplay.audit import AuditLog, AuditRow, Retention
from harness.audit import SMALL_SEGMENT, append

#: The retention the concurrent writers share: rotate every small segment, keep four.
BUDGET = Retention(segment_bytes=SMALL_SEGMENT, max_bytes=4 * SMALL_SEGMENT)


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


def concurrent(path: Path, rows: int, name: str) -> None:
    """Open, say ``READY``, append once told (a line on stdin), say ``DONE`` and close once
    told again: the test holds both writers open together while they append."""
    log = AuditLog(path, retention=BUDGET)
    told = iter(sys.stdin)
    print("READY", flush=True)
    next(told)
    for i in range(rows):
        log.append(AuditRow(
            at=1_800_000_000.0 + i, outcome="accepted", code=None, warning=None, msg_type=1,
            sender="op", sender_verified=True, msg_id=f"{name}-{i}",
        ))  # fmt: skip
        sys.stdout.write(f"{name}-{i}\n")
        sys.stdout.flush()
    print("DONE", flush=True)
    next(told)
    log.close()


def main() -> None:
    if sys.argv[2] == "append":
        concurrent(Path(sys.argv[1]), int(sys.argv[3]), sys.argv[4])
        return
    log = StoppingLog(Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]))
    for i in range(1_000_000):
        seq = append(log, i)
        sys.stdout.write(f"{seq}\n")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
