"""One atheris target in this process: ``python -m tests.fuzz.one TARGET [libFuzzer args]``."""

from __future__ import annotations

import sys
from pathlib import Path

import atheris

with atheris.instrument_imports(include=["antireplay", "tests.fuzz"]):
    from tests.fuzz.targets import TARGETS, seeds


def main() -> None:
    name, work = sys.argv[1], Path(sys.argv[2])
    for index, seed in enumerate(seeds(name)):
        (work / f"seed-{index}").write_bytes(seed)
    atheris.Setup([sys.argv[0], *sys.argv[2:]], TARGETS[name])
    atheris.Fuzz()


if __name__ == "__main__":
    main()
