"""Where a request's CPU goes: ``antireplay serve`` with per-stage and per-thread CPU counters.

Run by ``bench_gateway``'s ``stages`` row as ``python -m benchmarks._gateway_stages OUT
serve ...`` (the arguments after ``OUT`` are the CLI's).  Before the gateway starts, each
stage's function is wrapped to add the CPU time its calling thread spent in it
(``time.thread_time_ns``, about 0.2 µs per call) to a counter; ``SIGUSR1`` writes the
counters, their call counts and every thread's CPU so far (``pthread_getcpuclockid`` of
each live thread, by thread name) to ``OUT`` as JSON.  The row signals before and after a
wrk run and divides the differences by the requests answered.

Stages (where they run): *parse* and *replay check* (the event loop), *signature* (the
core's ``authenticate``: the Ed25519 verify, key lookup and scopes; a receive worker),
*commit + row* (the SQLite committer's batch: the entry and, paired, its audit row),
*audit drain* (the audit writer moving rows from the outbox into the chained trail),
*answer* (the COMMAND_ACK or NACK built and sent), *metrics* (``Metrics.observe``),
*refusal row* (the refusal auditor's admission and its row).  What the loop thread spends
beyond its stages is HTTP (uvicorn, Starlette), the forwarder and the hand-offs.

ESTOPs are timed inside the gateway too: from the guard's first look at the request to its
answer sent (``GuardMiddleware.__call__``), for each request whose check took the urgent
lane; the snapshot's ``estop_ms`` lists them, so a row can set the client's timing beside
the gateway's (the client on a saturated 2-core box waits for a core too).
"""

from __future__ import annotations

import asyncio
import functools
import json
import os
import signal
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from benchmarks._gateway_load import Run, Server

#: Stage name -> (module, attribute path) of the function timed.
STAGES: dict[str, tuple[str, str]] = {
    "parse": ("antireplay.rcan.steps", "Steps.parse"),
    "replay check": ("antireplay.rcan.receive_shared", "ReceiverBase._check"),
    "signature": ("antireplay.rcan.steps", "Steps.authenticate"),
    "commit + row": ("antireplay.state.sqlite", "SqliteStore._commit_batch"),
    "audit drain": ("antireplay.audit.writer", "AuditLog._write_batch"),
    "accept": ("antireplay.rcan.receive_shared", "ReceiverBase._accept"),
    "refusal row": ("antireplay.rcan.receive_shared", "ReceiverBase._refusal_row"),
    "answer": ("antireplay.http.guard", "answer"),
    "answer ": ("antireplay.http.upstream", "answer"),  # the same, bound by name there
    "forwarded envelope": ("antireplay.http.guard", "as_forwarded"),
    "metrics": ("antireplay.http.metrics", "Metrics.observe"),
}

_ns: dict[str, int] = defaultdict(int)
_calls: dict[str, int] = defaultdict(int)
#: In-gateway milliseconds of each request that took the urgent lane (an ESTOP's).
_estop_ms: list[float] = []
_urgent: set[asyncio.Task[Any]] = set()


def _timed(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    clock = time.thread_time_ns

    if _is_async(fn):

        @functools.wraps(fn)
        async def timed_async(*args: Any, **kwargs: Any) -> Any:
            # Only the synchronous part before the first await is this thread's to count;
            # an awaited answer is two sends: count the call, time the whole on this thread.
            start = clock()
            try:
                return await fn(*args, **kwargs)
            finally:
                _ns[name] += clock() - start
                _calls[name] += 1

        return timed_async

    @functools.wraps(fn)
    def timed(*args: Any, **kwargs: Any) -> Any:
        start = clock()
        try:
            return fn(*args, **kwargs)
        finally:
            _ns[name] += clock() - start
            _calls[name] += 1

    return timed


def _is_async(fn: Callable[..., Any]) -> bool:
    import inspect  # noqa: PLC0415 - once per stage

    return inspect.iscoroutinefunction(fn)


def install() -> None:
    """Wrap every stage's function (before the gateway imports its names)."""
    import importlib  # noqa: PLC0415

    for name, (module_name, path) in STAGES.items():
        module = importlib.import_module(module_name)
        owner: Any = module
        *parents, attr = path.split(".")
        for parent in parents:
            owner = getattr(owner, parent)
        fn = getattr(owner, attr)
        if not hasattr(fn, "_stage"):  # bound by name before it was wrapped: wrap there too
            timed = _timed(name.strip(), fn)
            timed._stage = name  # type: ignore[attr-defined]
            setattr(owner, attr, timed)


def install_estop_timer() -> None:
    """Time each urgent request from the guard's first look to its answer."""
    from antireplay.http.guard import GuardBase  # noqa: PLC0415
    from antireplay.http.middleware import GuardMiddleware  # noqa: PLC0415

    first, call = GuardBase._first, GuardMiddleware.__call__

    async def marked(self: GuardBase, fn: Callable[..., Any], *args: Any) -> Any:
        task = asyncio.current_task()
        if task is not None:
            _urgent.add(task)
        return await first(self, fn, *args)

    async def timed(self: GuardMiddleware, scope: Any, receive: Any, send: Any) -> None:
        start = time.perf_counter()
        try:
            await call(self, scope, receive, send)
        finally:
            task = asyncio.current_task()
            if task in _urgent:
                _urgent.discard(task)
                _estop_ms.append((time.perf_counter() - start) * 1e3)

    GuardBase._first = marked  # type: ignore[method-assign]
    GuardMiddleware.__call__ = timed  # type: ignore[method-assign]


def threads_cpu_ns() -> dict[str, int]:
    """Every live thread's CPU so far, by name (numbered names folded: ``receive-0`` ...)."""
    out: dict[str, int] = defaultdict(int)
    for thread in threading.enumerate():
        if thread.ident is None:
            continue
        try:
            cpu = time.clock_gettime_ns(time.pthread_getcpuclockid(thread.ident))
        except (OSError, ProcessLookupError):
            continue
        name = thread.name.split(":")[0].rstrip("0123456789-")
        out["event loop" if thread is threading.main_thread() else name] += cpu
    return dict(out)


def snapshot() -> dict[str, Any]:
    return {"stages": dict(_ns), "calls": dict(_calls), "threads": threads_cpu_ns(),
            "estop_ms": list(_estop_ms)}  # fmt: skip


def profile(server: Server, out: Path) -> dict[str, Any]:
    """The stage and thread counters of a gateway under :mod:`benchmarks._gateway_stages`."""
    out.unlink(missing_ok=True)
    os.kill(server.pid, signal.SIGUSR1)
    deadline = time.monotonic() + 10
    while not out.exists() or not out.read_text().endswith("}"):
        if time.monotonic() > deadline:
            raise SystemExit(f"{server.name}: no stage counters written")
        time.sleep(0.02)
    found: dict[str, Any] = json.loads(out.read_text())
    return found


def stage_lines(label: str, before: dict[str, Any], after: dict[str, Any], run: Run) -> list[str]:
    """CPU µs per request of each stage and thread over one run (what ``after`` adds)."""
    n = max(run.requests, 1)

    def per_request(kind: str) -> dict[str, float]:
        was = before.get(kind, {})
        return {k: (v - was.get(k, 0)) / n / 1e3 for k, v in after.get(kind, {}).items()}

    staged, threads = per_request("stages"), per_request("threads")
    calls = {k: (v - before["calls"].get(k, 0)) / n for k, v in after["calls"].items()}
    lines = [f"CPU per request, {label} ({run.requests} requests, {run.rps:,.0f} req/s;"
             f" process {run.cpu_ms * 1e3:.0f} µs):"]  # fmt: skip
    by_cost = sorted(staged.items(), key=lambda kv: -kv[1])
    lines += [f"  stage  {name:<20} {us:7.1f} µs  ({calls.get(name, 0):.2f} calls)"
              for name, us in by_cost if us > 0.05]  # fmt: skip
    lines += [f"  thread {name:<20} {us:7.1f} µs" for name, us in
              sorted(threads.items(), key=lambda kv: -kv[1]) if us > 0.05]  # fmt: skip
    on_loop = ("parse", "replay check", "accept", "refusal row", "answer",
               "forwarded envelope", "metrics")  # fmt: skip
    rest = threads.get("event loop", 0.0) - sum(staged.get(s, 0.0) for s in on_loop)
    lines.append(f"  event loop beyond its stages (HTTP, hand-offs, the rest): {rest:.1f} µs")
    return lines


def main() -> None:
    out, args = Path(sys.argv[1]), sys.argv[2:]

    def dump(_signum: int, _frame: FrameType | None) -> None:
        out.write_text(json.dumps(snapshot()))

    install()
    install_estop_timer()
    signal.signal(signal.SIGUSR1, dump)
    from antireplay.cli import main as cli  # noqa: PLC0415 - after the stages are wrapped

    sys.argv = ["antireplay", *args]
    cli()


if __name__ == "__main__":
    main()
