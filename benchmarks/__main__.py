"""Run the benchmarks: ``python -m benchmarks`` (or ``antireplay bench``) runs them all,
``python -m benchmarks NAME...`` the named ones (``window``, ``bench_window``, ``pq-radio``);
options after the names go to the one benchmark named (``python -m benchmarks pq-radio
--commands 50``), whose ``main`` takes its argument list."""

from __future__ import annotations

import importlib
import pkgutil
import sys

import benchmarks

#: Every ``bench_*`` module of this package (``antireplay bench`` finds the same files).
MODULES = sorted(
    m.name for m in pkgutil.iter_modules(benchmarks.__path__) if m.name.startswith("bench_")
)


def module_name(name: str) -> str:
    """``pq-radio``, ``pq_radio`` and ``bench_pq_radio`` all name ``bench_pq_radio``."""
    name = name.replace("-", "_")
    return name if name.startswith("bench_") else f"bench_{name}"


def selected(names: list[str]) -> list[str]:
    """The modules ``names`` ask for (all when empty); an unknown name exits with the list."""
    if not names:
        return MODULES
    wanted = [module_name(n) for n in names]
    unknown = [n for n in wanted if n not in MODULES]
    if unknown:
        raise SystemExit(
            f"unknown benchmark {', '.join(unknown)}; choose from {', '.join(MODULES)}"
        )
    return wanted


def split(argv: list[str]) -> tuple[list[str], list[str]]:
    """The names, then the options (from the first argument starting with ``-``)."""
    first = next((i for i, arg in enumerate(argv) if arg.startswith("-")), len(argv))
    return argv[:first], argv[first:]


def main(names: list[str] | None = None) -> None:
    names, options = split(sys.argv[1:] if names is None else names)
    chosen = selected(names)
    if options and len(chosen) != 1:
        raise SystemExit(f"options ({' '.join(options)}) go to exactly one named benchmark")
    for name in chosen:
        print(f"\n== {name} ==", flush=True)
        module = importlib.import_module(f"benchmarks.{name}")
        if options:
            module.main(options)
        else:
            module.main()


if __name__ == "__main__":
    main()
