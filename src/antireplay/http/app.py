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
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

from antireplay.http.metrics import Metrics
from antireplay.http.middleware import GuardMiddleware
from antireplay.http.readiness import audit_problem, fence_notice, readiness, ready_endpoint
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

    async def summaries() -> None:
        """The folded refusals' summary rows, every interval (queued, not awaited)."""
        while True:
            await asyncio.sleep(receiver.refusals.flush_s)
            receiver.refusals.flush()

    @asynccontextmanager
    async def lifespan(served: Starlette) -> AsyncIterator[None]:
        timer = asyncio.create_task(summaries())
        yield  # the guard stops its workers once this has run
        timer.cancel()
        keys = getattr(served.state, "keys", None)  # the key watcher wiring may have started
        if keys is not None:
            keys.stop()
        receiver.close()

    app = Starlette(
        routes=[
            Route("/v1/messages", forward, methods=["POST"]),
            Route("/healthz", healthz, methods=["GET"]),
            Route("/readyz", ready_endpoint(receiver), methods=["GET"]),
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


__all__ = ["audit_problem", "fence_notice", "gateway_app", "readiness"]
