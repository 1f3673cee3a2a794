"""Subprocess helpers for the multi-process store tests and the kill -9 tests."""

from __future__ import annotations

import sys
from collections.abc import Callable


def emit_forever(produce: Callable[[], int]) -> None:
    """Print one value per line, flushed, until the test kills this process."""
    out = sys.stdout
    while True:
        out.write(f"{produce()}\n")
        out.flush()
