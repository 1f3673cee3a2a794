"""The HTTP gateway: a thin Starlette adapter in front of a robot's command API.

``POST /v1/messages`` takes one RCAN envelope (``application/json``, at most
``max_body_bytes``), runs :class:`~antireplay.pipeline.Receiver` (built from the
configuration by :func:`antireplay.wiring.build_receiver`), and either
forwards the accepted message upstream (the canonical re-encoding, never the
raw bytes) and answers with the upstream's result, or answers with the
COMMAND_NACK and its HTTP status.  ``GET /healthz`` and ``GET /metrics``
(Prometheus) complete it.  No rule lives here: every decision is the
pipeline's, except transport framing: a request that carries both
``Content-Length`` and ``Transfer-Encoding`` is refused with 400 and the
connection closed (RFC 9112 §6.1), on every route, because a proxy in front
that honours the other header would see a different request boundary (the
request-smuggling shape).  h11 (uvicorn's default) hands both headers to the
app and frames by ``Transfer-Encoding``; httptools refuses such requests
itself.  Every audit record is committed (fsync) before the response is
sent, so a graceful or abrupt shutdown loses no answered message's record.

With no configuration the gateway runs on the embedded default: SQLite state
and audit under ``./.antireplay/`` and a generated demo key pair
(:func:`embedded_default`).
"""

from __future__ import annotations

import asyncio
import importlib
import json
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from concurrent.futures import Future
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import httpx
from cryptography.hazmat.primitives.asymmetric import ed25519
from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.middleware import Middleware
from starlette.requests import ClientDisconnect, Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route
from starlette.types import ASGIApp, Receive, Scope, Send

from antireplay.auth import write_key_pair
from antireplay.clock import Clock, resolve
from antireplay.config import AppConfig, KeyConfig
from antireplay.envelope import encode
from antireplay.errors import ConfigError, InvalidEnvelopeError, StateUnavailableError
from antireplay.groupcommit import GroupCommitter
from antireplay.pipeline import Outcome, Receiver
from antireplay.wiring import build_receiver

DEMO_KID = "demo-operator"
Upstream = Callable[[dict[str, Any]], Awaitable[tuple[int, Any]]]


def embedded_default(state_dir: Path = Path(".antireplay")) -> AppConfig:
    """SQLite state and audit under ``state_dir`` and a demo Ed25519 key pair (made once)."""
    state_dir.mkdir(parents=True, exist_ok=True)
    private, public = state_dir / f"{DEMO_KID}.key.pem", state_dir / f"{DEMO_KID}.pub.pem"
    if not private.exists():
        write_key_pair(ed25519.Ed25519PrivateKey.generate(), private, public)
    return AppConfig(
        store=f"sqlite:{state_dir / 'state.db'}",
        audit=str(state_dir / "audit.db"),
        keys=[
            KeyConfig(
                kid=DEMO_KID,
                owner="operator",
                alg="ed25519",
                public_keys=[str(public)],
                scopes=["control", "safety"],
            )
        ],
    )


def resolve_upstream(spec: str | None, timeout_s: float) -> Upstream | None:
    """``http(s)://…`` → POST via httpx; ``module:function`` → call it; None → answer locally."""
    if spec is None:
        return None
    if spec.startswith(("http://", "https://")):
        client = httpx.AsyncClient(timeout=timeout_s)

        async def post(envelope: dict[str, Any]) -> tuple[int, Any]:
            reply = await client.post(spec, json=envelope)
            try:
                return reply.status_code, reply.json()
            except ValueError:
                return reply.status_code, {"body": reply.text[:1000]}

        return post
    module_name, _, attr = spec.partition(":")
    try:
        func = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError, ValueError) as exc:
        raise ConfigError("upstream", spec, f"http(s)://URL or module:function ({exc})") from None

    async def call(envelope: dict[str, Any]) -> tuple[int, Any]:
        return 200, await run_in_threadpool(func, envelope)

    return call


class Metrics:
    """Prometheus metrics of one gateway (its own registry, so tests can run several)."""

    def __init__(self, receiver: Receiver) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.accepted = Counter("antireplay_accepted", "Accepted messages", registry=r)
        self.rejected = Counter("antireplay_rejected", "Rejected messages", ["code"], registry=r)
        self.warnings = Counter(
            "antireplay_warnings", "Accepted with warning", ["warning"], registry=r
        )
        self.latency = Histogram("antireplay_latency_seconds", "Pipeline latency", registry=r)
        self.store_errors = Counter(
            "antireplay_store_errors", "STATE_UNAVAILABLE answers", registry=r
        )
        self.upstream_errors = Counter(
            "antireplay_upstream_errors", "Upstream failures", registry=r
        )
        r.register(StateCollector(receiver))

    def observe(self, outcome: Outcome, seconds: float) -> None:
        self.latency.observe(seconds)
        if outcome.accepted:
            self.accepted.inc()
            if outcome.warning:
                self.warnings.labels(outcome.warning).inc()
        else:
            self.rejected.labels(outcome.code or "UNKNOWN").inc()
            if outcome.code == "STATE_UNAVAILABLE":
                self.store_errors.inc()


class StateCollector(Collector):
    """The replay state of the backend actually in use, read at scrape time."""

    def __init__(self, receiver: Receiver) -> None:
        self.receiver = receiver

    def collect(self) -> Iterator[Metric]:
        cache = self.receiver.cache
        try:
            status = cache.store.status()
        except StateUnavailableError:
            status = {}
        backend = cache.store.backend
        for name, doc, key in (
            ("antireplay_cache_entries", "Entries in the seen-set", "entries"),
            ("antireplay_state_watermark_seconds", "Largest expiry forgotten", "watermark"),
            ("antireplay_state_fence_seconds", "Restart/data-loss fence", "fence"),
        ):
            gauge = GaugeMetricFamily(name, doc, labels=["backend"])
            gauge.add_metric([backend], status.get(key, float("nan")))
            yield gauge
        for name, doc, key in (
            ("antireplay_watermark_raises", "Entries evicted early (saturation)", "evictions"),
            ("antireplay_state_data_loss", "Data-loss events noticed", "data_loss_events"),
        ):
            counter = CounterMetricFamily(name, doc, labels=["backend"])
            counter.add_metric([backend], status.get(key, float("nan")))
            yield counter
        refusals = CounterMetricFamily(
            "antireplay_replay_refusals", "Window refusals by cause", labels=["cause"]
        )
        for cause, count in sorted(cache.refusals.items()):
            refusals.add_metric([cause], count)
        yield refusals
        fence = CounterMetricFamily(
            "antireplay_restart_fence_rejections", "Refused by the restart/data-loss fence"
        )
        fence.add_metric([], cache.refusals["restart_fence"])
        yield fence
        batches = CounterMetricFamily(
            "antireplay_group_commit_batches", "Durable commits (one fsync each)", labels=["log"]
        )
        operations = CounterMetricFamily(
            "antireplay_group_commit_operations", "Records in those commits", labels=["log"]
        )
        for name, owner in (("state", cache.store), ("audit", self.receiver.audit)):
            committer = getattr(owner, "group_commit", None)
            if isinstance(committer, GroupCommitter):
                batches.add_metric([name], committer.batches)
                operations.add_metric([name], committer.operations)
        yield batches
        yield operations


class RefuseAmbiguousFraming:
    """ASGI middleware: both Content-Length and Transfer-Encoding -> 400 and close (RFC 9112)."""

    def __init__(self, app: ASGIApp, nack_type: int = 18) -> None:
        self.app = app
        self.nack_type = nack_type

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            names = {name.lower() for name, _ in scope["headers"]}
            if b"content-length" in names and b"transfer-encoding" in names:
                reason = "both Content-Length and Transfer-Encoding (RFC 9112 section 6.1)"
                nack = InvalidEnvelopeError(reason).to_nack(None, nack_type=self.nack_type)
                refusal = JSONResponse(nack, status_code=400, headers={"connection": "close"})
                await refusal(scope, receive, send)
                return
        await self.app(scope, receive, send)


async def _audited(receiver: Receiver, outcome: Outcome, pending: Future[int] | None) -> Outcome:
    """Wait, without a thread, until the outcome's audit row is durable (answers wait for it)."""
    if pending is not None:
        try:
            await asyncio.wrap_future(pending)
        except Exception:  # the rejection stands; it could not be recorded
            receiver.stats.audit_failures += 1
    return outcome


def _nack(outcome: Outcome) -> JSONResponse:
    return JSONResponse(outcome.nack, status_code=outcome.status)


def create_app(config: AppConfig, *, clock: Clock | None = None) -> Starlette:
    """The gateway application for ``config``."""
    receiver = build_receiver(config, clock)
    upstream = resolve_upstream(config.upstream, config.upstream_timeout_s)
    metrics = Metrics(receiver)
    limit = config.max_body_bytes
    ticker = resolve(None)

    def _refuse(status: int, reason: str) -> JSONResponse:
        """Transport-level refusals: the same NACK as the pipeline's, with the configured type."""
        nack = InvalidEnvelopeError(reason).to_nack(None, nack_type=config.security.nack_type)
        return JSONResponse(nack, status_code=status)

    async def messages(request: Request) -> Response:  # noqa: PLR0911 - one answer per case
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype != "application/json":
            return _refuse(415, "content-type must be application/json")
        declared = request.headers.get("content-length")
        if declared is not None and not (declared.isascii() and declared.isdigit()):
            return _refuse(400, "invalid content-length")
        digits = declared.lstrip("0") if declared is not None else ""
        if len(digits) > len(str(limit)) or (digits and int(digits) > limit):
            return _refuse(413, f"body larger than {limit} bytes")
        body = bytearray()
        try:
            async for chunk in request.stream():
                body += chunk
                if len(body) > limit:
                    return _refuse(413, f"body larger than {limit} bytes")
        except ClientDisconnect:
            return _refuse(400, "client disconnected")
        started = ticker.monotonic()
        raw = bytes(body)
        known = receiver.reject_known_copy(raw)  # on the loop: no parse, no thread hop
        if known is not None:
            outcome = await _audited(receiver, *known)
            metrics.observe(outcome, ticker.monotonic() - started)
            return _nack(outcome)
        outcome = await run_in_threadpool(receiver.receive, raw, dict(request.headers))
        metrics.observe(outcome, ticker.monotonic() - started)
        if not outcome.accepted:
            return _nack(outcome)
        assert outcome.envelope is not None
        answer: dict[str, Any] = {"accepted": True, "msg_id": outcome.msg_id}
        if outcome.warning:
            answer["warning"] = outcome.warning
        if upstream is None:
            return JSONResponse(answer)
        try:
            status, result = await upstream(json.loads(encode(outcome.envelope)))
        except Exception as exc:
            metrics.upstream_errors.inc()
            return JSONResponse({**answer, "upstream_error": type(exc).__name__}, status_code=502)
        return JSONResponse({**answer, "result": result}, status_code=status)

    async def healthz(_: Request) -> Response:
        return JSONResponse({"status": "ok", "time": time.time()})

    async def metrics_endpoint(_: Request) -> Response:
        body = await run_in_threadpool(generate_latest, metrics.registry)  # may read the store
        return Response(body, media_type="text/plain; version=0.0.4")

    @asynccontextmanager
    async def lifespan(_: Starlette) -> AsyncIterator[None]:
        yield
        if receiver.audit is not None:
            receiver.audit.close()

    app = Starlette(
        routes=[
            Route("/v1/messages", messages, methods=["POST"]),
            Route("/healthz", healthz, methods=["GET"]),
            Route("/metrics", metrics_endpoint, methods=["GET"]),
        ],
        lifespan=lifespan,
        middleware=[Middleware(RefuseAmbiguousFraming, nack_type=config.security.nack_type)],
    )
    app.state.receiver = receiver
    app.state.metrics = metrics
    return app
