"""Shared timing helper for the benchmarks: medians of repeated batches."""

from __future__ import annotations

import gc
import statistics
import time
from collections.abc import Callable


def per_op_ns(action: Callable[[], object], batch: int, repeats: int = 7) -> float:
    """Median nanoseconds per call of ``action`` over ``repeats`` batches."""
    samples = []
    for _ in range(repeats):
        gc.collect()
        start = time.perf_counter_ns()
        for _ in range(batch):
            action()
        samples.append((time.perf_counter_ns() - start) / batch)
    return statistics.median(samples)


#: Runs batch number ``r`` of one contender (see :func:`interleaved_ns_per_op`).
Batch = Callable[[int], None]


def interleaved_ns_per_op(contenders: list[tuple[Batch, int]], repeats: int = 7) -> list[float]:
    """Median ns per operation of each ``(run_batch, batch size)``, batches interleaved.

    Batch r of every contender runs before batch r + 1 of any, so a burst of noise on
    this shared machine lands on all of them alike instead of skewing one ratio.
    """
    samples: list[list[float]] = [[] for _ in contenders]
    for r in range(repeats):
        for (run_batch, batch), out in zip(contenders, samples, strict=True):
            gc.collect()
            start = time.perf_counter_ns()
            run_batch(r)
            out.append((time.perf_counter_ns() - start) / batch)
    return [statistics.median(out) for out in samples]


def rate(ns: float) -> str:
    return f"{1e9 / ns:>12,.0f}/s"


def rejected(action: Callable[[], object], *errors: type[Exception]) -> Callable[[], None]:
    """``action`` wrapped so a benchmark loop proves every call is refused with ``errors``."""

    def attempt() -> None:
        try:
            action()
        except errors:
            return
        raise AssertionError("a replay was accepted")

    return attempt
