"""The gateway application: a guard around its forwarding app, and the operator's routes.

:func:`gateway_app` takes built objects (the receiver, the resolved upstream and its time
budget) and returns a Starlette app: ``POST /v1/messages`` is
:class:`~antireplay.http.middleware.GuardMiddleware` in front of
:class:`~antireplay.http.upstream.Forward`, so an accepted message goes straight to the
forwarder (no routing on the hot path) and the gateway answers exactly what the middleware
answers inside anybody's app.  ``GET /healthz`` is liveness (the process answers);
``GET /readyz`` is readiness: the replay store could take a commit and the audit trail an
append now, free space under the trail is above its second floor, and the store's fence
(a start with no history, a loss) no longer lies ahead, else 503 with the reason, since
every command would be refused too (``fenced until T``: a fresh ESTOP still passes); the
folded refusals' summary rows are written every interval by a lifespan timer (and at
shutdown);
``GET /metrics`` is Prometheus; ``GET /`` and ``GET /status.json`` are the read-only status
page (:mod:`antireplay.http.status`).  The readiness probes record nothing (the store's
``ready()``: a read, the eviction policy, a write lock taken and released; the same lock on
the audit file), so a probe never notices a store's data loss in place of the commit that
fences and audits it.  Every audit record is committed (fsync) before the response is sent,
so a graceful or abrupt shutdown loses no answered message's record; lifespan shutdown
stops the guard's workers, then closes the audit trail.
"""

from __future__ import annotations

import asyncio
import sqlite3
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from datetime import datetime, timezone

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

from antireplay.audit import AuditLog
from antireplay.http.metrics import Metrics
from antireplay.http.middleware import GuardMiddleware
from antireplay.http.status import rolled_back
from antireplay.http.status import routes as status_routes
from antireplay.http.upstream import Forward, Upstream
from antireplay.rcan.receive import Receiver


def gateway_app(receiver: Receiver, upstream: Upstream | None, timeout_s: float) -> Starlette:
    """The gateway on ``receiver``: a :class:`GuardMiddleware` in front of an app whose
    ``POST /v1/messages`` forwards what the guard verified (one code path by construction)."""
    metrics = Metrics(receiver)
    forward = Forward(upstream, metrics, receiver, timeout_s)

    async def healthz(_: Request) -> Response:
        return JSONResponse({"status": "ok", "time": time.time()})

    async def readyz(_: Request) -> Response:
        reason = await run_in_threadpool(readiness, receiver)
        if reason is not None:
            return JSONResponse({"status": "unavailable", "reason": reason}, status_code=503)
        warning = None if receiver.audit is None else rolled_back(receiver.audit)
        return JSONResponse({"status": "ready", **({"warning": warning} if warning else {})})

    async def summaries() -> None:
        """The folded refusals' summary rows, every interval (queued, not awaited)."""
        while True:
            await asyncio.sleep(receiver.refusals.flush_s)
            receiver.refusals.flush()

    @asynccontextmanager
    async def lifespan(_: Starlette) -> AsyncIterator[None]:
        timer = asyncio.create_task(summaries())
        yield  # the guard stops its workers once this has run
        timer.cancel()
        receiver.close()

    app = Starlette(
        routes=[
            Route("/v1/messages", forward, methods=["POST"]),
            Route("/healthz", healthz, methods=["GET"]),
            Route("/readyz", readyz, methods=["GET"]),
            Route("/metrics", metrics.endpoint, methods=["GET"]),
            *status_routes(receiver, metrics.registry, readiness),  # GET /, GET /status.json
        ],
        lifespan=lifespan,
        middleware=[
            Middleware(GuardMiddleware, receiver=receiver, metrics=metrics, accepted=forward)
        ],  # an accepted message goes straight to the forwarder (no routing on the hot path)
    )
    app.state.receiver = receiver
    app.state.metrics = metrics
    return app


def readiness(receiver: Receiver) -> str | None:
    """Why the gateway cannot serve commands now (store or audit trail), ``None`` if it can.

    Blocking I/O (run it in a thread); records nothing."""
    try:
        receiver.cache.store.ready()
    except Exception as exc:  # any backend's failure is the reason, never a 500
        return f"store: {exc}"
    fenced = fence_notice(receiver)
    if fenced is not None:
        return fenced
    disk = None if receiver.space is None else receiver.space.reason()
    if disk is not None:
        return disk
    return None if receiver.audit is None else audit_problem(receiver.audit)


def fence_notice(receiver: Receiver) -> str | None:
    """While the store's fence lies ahead (its start with no history, a loss it noticed),
    every command stamped now is refused as ``restart_fence``: say until when, and why
    (``None`` once a command stamped now passes; a fresh ESTOP passes throughout)."""
    cache = receiver.cache
    until = cache.store.fence() + cache.policy.skew_s
    if receiver.clock.wall() > until:
        return None
    when = datetime.fromtimestamp(until, timezone.utc).isoformat(timespec="milliseconds")
    why = getattr(cache.store, "loss_reason", None) or "the store's start (no history)"
    return f"fenced until {when} ({until:.3f}): {why}; a fresh ESTOP still passes"


def audit_problem(audit: AuditLog, timeout_s: float = 1.0) -> str | None:
    """Why ``audit`` could not take an append now, or ``None``: its file is still there and
    its write lock can be taken within ``timeout_s`` (taken and released, nothing written),
    and its head checkpoint file is writable."""
    try:
        db = sqlite3.connect(f"file:{audit.path}?mode=rw", uri=True, timeout=timeout_s)
        try:
            db.execute("BEGIN IMMEDIATE")
            db.execute("ROLLBACK")
        finally:
            db.close()
    except sqlite3.Error as exc:
        return f"audit {audit.path}: {exc}"
    try:
        with audit.anchor.path.open("r+b"):
            pass
    except OSError as exc:
        return f"audit head {audit.anchor.path}: {exc.strerror or exc}"
    return None
