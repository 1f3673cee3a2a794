"""Subprocess for the kill -9 tests: hand out persistent counter values until killed."""

from __future__ import annotations

import sys

from antireplay.counters import NonceCounter
from tests.helpers import emit_forever


def main() -> None:
    counter = NonceCounter.persistent(sys.argv[1], lease=int(sys.argv[2]))
    emit_forever(counter.next)


if __name__ == "__main__":
    main()
