"""Run every benchmark: ``python -m benchmarks`` (or ``antireplay bench``)."""

from __future__ import annotations

import importlib

MODULES = [
    "bench_window", "bench_counters", "bench_epochs", "bench_stores", "bench_pipeline",
    "bench_gateway", "bench_mavlink",
]  # fmt: skip


def main() -> None:
    for name in MODULES:
        print(f"\n== {name} ==", flush=True)
        importlib.import_module(f"benchmarks.{name}").main()


if __name__ == "__main__":
    main()
