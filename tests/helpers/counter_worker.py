"""Subprocess for the kill -9 tests: hand out persistent counter values until killed."""

from __future__ import annotations

import sys

from antireplay.counters import NonceCounter


def main() -> None:
    counter = NonceCounter.persistent(sys.argv[1], lease=int(sys.argv[2]))
    out = sys.stdout
    while True:
        out.write(f"{counter.next()}\n")
        out.flush()


if __name__ == "__main__":
    main()
