"""Run the benchmarks: ``python -m benchmarks`` (or ``antireplay bench``) runs them all,
``python -m benchmarks NAME...`` the named ones (``window`` or ``bench_window``); arguments
that start with ``-`` (``--seconds=20``) are left for the benchmarks to read."""

from __future__ import annotations

import importlib
import pkgutil
import sys

import benchmarks

#: Every ``bench_*`` module of this package (``antireplay bench`` finds the same files).
MODULES = sorted(
    m.name for m in pkgutil.iter_modules(benchmarks.__path__) if m.name.startswith("bench_")
)


def selected(names: list[str]) -> list[str]:
    """The modules ``names`` ask for (all when empty); an unknown name exits with the list."""
    if not names:
        return MODULES
    wanted = [n if n.startswith("bench_") else f"bench_{n}" for n in names]
    unknown = [n for n in wanted if n not in MODULES]
    if unknown:
        raise SystemExit(
            f"unknown benchmark {', '.join(unknown)}; choose from {', '.join(MODULES)}"
        )
    return wanted


def main(names: list[str] | None = None) -> None:
    asked = [a for a in sys.argv[1:] if not a.startswith("-")]  # options: for the module
    for name in selected(asked if names is None else names):
        print(f"\n== {name} ==", flush=True)
        importlib.import_module(f"benchmarks.{name}").main()


if __name__ == "__main__":
    main()
