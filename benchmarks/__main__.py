"""Run every benchmark: ``python -m benchmarks`` (or ``antireplay bench``)."""

from __future__ import annotations

import importlib
import pkgutil

import benchmarks

#: Every ``bench_*`` module of this package (``antireplay bench`` finds the same files).
MODULES = sorted(
    m.name for m in pkgutil.iter_modules(benchmarks.__path__) if m.name.startswith("bench_")
)


def main() -> None:
    for name in MODULES:
        print(f"\n== {name} ==", flush=True)
        importlib.import_module(f"benchmarks.{name}").main()


if __name__ == "__main__":
    main()
