"""Subprocess for the kill -9 tests: hand out persistent counter values until killed."""

from __future__ import annotations

import sys

from antireplay.state.ceilings import persistent_counter
from harness.workers import emit_forever


def main() -> None:
    counter = persistent_counter(sys.argv[1], lease=int(sys.argv[2]))
    emit_forever(counter.next)


if __name__ == "__main__":
    main()
