"""The HTTP gateway: a thin Starlette adapter in front of a robot's command API.

``POST /v1/messages`` takes one RCAN envelope (``application/json``, at most
``max_body_bytes``), runs :class:`~antireplay.pipeline.Receiver` (built from the
configuration by :func:`antireplay.wiring.build_receiver`), and either
forwards the accepted message upstream (the canonical re-encoding, never the
raw bytes) and answers with the upstream's result, or answers with the
COMMAND_NACK and its HTTP status.  ``GET /healthz`` (liveness: the process
answers), ``GET /`` and ``GET /status.json`` (the read-only status page,
:mod:`antireplay.status`), ``GET /readyz`` (readiness: the replay store could take a commit and
the audit trail an append now, else 503 with the reason, since every command
would get 503 too) and ``GET /metrics`` (Prometheus) complete it.  The
readiness probes record nothing (the store's ``ready()``: a read, the eviction
policy, a write lock taken and released; the same lock on the audit file), so
a probe never notices a store's data loss in place of the commit that fences
and audits it.  No rule lives here: every decision is the
pipeline's, except transport framing: a request that carries both
``Content-Length`` and ``Transfer-Encoding`` is refused with 400 and the
connection closed (RFC 9112 §6.1), on every route, because a proxy in front
that honours the other header would see a different request boundary (the
request-smuggling shape).  h11 (uvicorn's default) hands both headers to the
app and frames by ``Transfer-Encoding``; httptools refuses such requests
itself.  Every audit record is committed (fsync) before the response is
sent, so a graceful or abrupt shutdown loses no answered message's record.

``POST /v1/messages`` is answered by the front middleware itself (no routing,
no Request object), and a request holds a thread only while there is work for
one: a byte-identical replay is refused on the event loop; parsing, the store
read and the signature run in a few :class:`Workers`; the state commit and the
audit row are group-committed and awaited on the loop
(:meth:`~antireplay.pipeline.Receiver.receive_async`).

With no configuration the gateway runs on the embedded default: SQLite state
and audit under ``./.antireplay/`` and a generated demo key pair
(:func:`embedded_default`).
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import json
import queue
import sqlite3
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, Literal

import httpx
import msgspec
from cryptography.hazmat.primitives.asymmetric import ed25519
from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route
from starlette.types import ASGIApp, Receive, Scope, Send

from antireplay.answers import HeldAnswer
from antireplay.audit import AuditLog
from antireplay.auth import write_key_pair
from antireplay.clock import Clock, resolve
from antireplay.config import AppConfig, KeyConfig
from antireplay.envelope import encode
from antireplay.errors import (
    ConfigError,
    InvalidEnvelopeError,
    PayloadTooLargeError,
    ReplayAttackError,
    StateUnavailableError,
    UnsupportedMediaTypeError,
    UpstreamFailedError,
)
from antireplay.groupcommit import GroupCommitter
from antireplay.pipeline import Outcome, Pending, Receiver
from antireplay.status import routes as status_routes
from antireplay.wiring import build_receiver

DEMO_KID = "demo-operator"
#: Latency buckets from 50 µs (a check takes ~0.1 ms; an fsync a few ms) to 2.5 s.
LATENCY_BUCKETS = (
    0.00005, 0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5,
    1.0, 2.5, float("inf"),
)  # fmt: skip
_encode_json = msgspec.json.Encoder().encode
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


async def _forward(
    upstream: Upstream | None, outcome: Outcome, metrics: Metrics, nack_type: int
) -> tuple[int, dict[str, Any]]:
    """The answer to an accepted message: its COMMAND_ACK (readable by the rcan SDK) with
    the upstream's result, or 502 ``UPSTREAM_FAILED`` (the msg_id stays spent: README
    "Threat model")."""
    answer: dict[str, Any] = outcome.ack or {}
    if upstream is None:
        return 200, answer
    assert outcome.envelope is not None
    try:
        status, result = await upstream(json.loads(encode(outcome.envelope)))
    except Exception as exc:
        metrics.upstream_errors.inc()
        failed = UpstreamFailedError(type(exc).__name__, delivered=_delivered(exc))
        return 502, failed.to_nack(outcome.msg_id, nack_type=nack_type)
    return status, {**answer, "result": result}


def _delivered(exc: Exception) -> Literal["no", "unknown"]:
    """Whether a failed upstream call reached the upstream: ``"no"`` when no connection was
    made (nothing was sent), else ``"unknown"`` (sent, then failed or timed out)."""
    unsent = (httpx.ConnectError, httpx.ConnectTimeout, httpx.PoolTimeout)
    return "no" if isinstance(exc, unsent) else "unknown"


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
        self.latency = Histogram(
            "antireplay_latency_seconds", "Pipeline latency", buckets=LATENCY_BUCKETS, registry=r
        )
        self.store_errors = Counter(
            "antireplay_store_errors", "STATE_UNAVAILABLE answers", registry=r
        )
        self.upstream_errors = Counter(
            "antireplay_upstream_errors", "Upstream failures", registry=r
        )
        self.retries = Counter(
            "antireplay_retries_answered", "QoS retries given the original answer", registry=r
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
            if outcome.retry is not None:
                self.retries.inc()


class StateCollector(Collector):
    """The replay state of the backend actually in use, read at scrape time.  While the
    store is down its gauges are NaN (unknown) and its counters keep their last known
    value (a counter is never NaN: a rate over it would be NaN too); none known, no sample."""

    def __init__(self, receiver: Receiver) -> None:
        self.receiver = receiver
        self._counted: dict[str, float] = {}

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
            ("antireplay_watermark_raises_total", "Entries evicted early (full)", "evictions"),
            ("antireplay_state_data_loss_total", "Data-loss events noticed", "data_loss_events"),
        ):
            counter = CounterMetricFamily(name, doc, labels=["backend"])
            if key in status:
                self._counted[key] = status[key]
            if key in self._counted:
                counter.add_metric([backend], self._counted[key])
            yield counter
        refusals = CounterMetricFamily(
            "antireplay_replay_refusals", "Window refusals by cause", labels=["cause"]
        )
        for cause, count in sorted(cache.refusals.items()):
            refusals.add_metric([cause], count)
        yield refusals
        fence = CounterMetricFamily(
            "antireplay_restart_fence_rejections_total", "Refused by the restart/data-loss fence"
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
    """ASGI middleware in front of every route: both Content-Length and Transfer-Encoding
    -> 400 and close (RFC 9112); ``POST /v1/messages`` goes straight to ``messages`` (no
    routing, no Request object: the hot path); everything else to the Starlette app."""

    def __init__(self, app: ASGIApp, messages: Messages, nack_type: int = 18) -> None:
        self.app = app
        self.messages = messages
        self.nack_type = nack_type

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        ctype: bytes | None = None
        length: bytes | None = None
        chunked = False
        for raw_name, value in scope["headers"]:
            name = raw_name.lower()
            if name == b"content-type":
                ctype = value if ctype is None else ctype
            elif name == b"content-length":
                length = value if length is None else length
            elif name == b"transfer-encoding":
                chunked = True
        if length is not None and chunked:
            reason = "both Content-Length and Transfer-Encoding (RFC 9112 section 6.1)"
            nack = InvalidEnvelopeError(reason).to_nack(None, nack_type=self.nack_type)
            await _answer(send, 400, nack, close=True)
            return
        if scope["method"] == "POST" and _route_path(scope) == "/v1/messages":
            await self.messages(scope, receive, send, ctype, length)
            return
        await self.app(scope, receive, send)


Messages = Callable[[Scope, Receive, Send, bytes | None, bytes | None], Awaitable[None]]


def _route_path(scope: Scope) -> str:
    """The path the router would match (``root_path`` removed, as Starlette does)."""
    path: str = scope["path"]
    root: str = scope.get("root_path", "")
    return path[len(root) :] if root and path.startswith(root) else path


async def _answer(
    send: Send, status: int, content: object, held: HeldAnswer | None = None, *, close: bool = False
) -> None:
    """One JSON response (``content``, or its encoding as bytes; plus a held answer's
    headers), sent as two ASGI messages (what JSONResponse sends, cheaper)."""
    body = content if isinstance(content, bytes) else _encode_json(content)
    headers = [(b"content-type", b"application/json"), (b"content-length", b"%d" % len(body))]
    if close:
        headers.append((b"connection", b"close"))
    headers += [(k.encode("latin-1"), v.encode("latin-1")) for k, v in held.headers] if held else []
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


async def _settle(receiver: Receiver, workers: Workers, pending: Pending) -> Outcome:
    """Wait, without a thread, until the outcome's audit row is durable, then settle it."""
    failure: BaseException | None = None
    audit = pending.audit
    if audit is not None:
        try:
            await (audit if isinstance(audit, asyncio.Future) else asyncio.wrap_future(audit))
        except Exception as exc:  # settle() turns any failure into the answer
            failure = exc
    if failure is not None and pending.outcome.accepted:  # its refusal is audited: blocks
        outcome: Outcome = await workers(receiver.settle, pending, failure)
        return outcome
    return receiver.settle(pending, failure)


def _framing_refusal(
    ctype: bytes | None, length: bytes | None, limit: int
) -> ReplayAttackError | None:
    """The typed refusal of the declared content type or length, ``None`` if fine."""
    if (ctype or b"").decode("latin-1").split(";")[0].strip().lower() != "application/json":
        return UnsupportedMediaTypeError("content-type must be application/json")
    if length is None:
        return None
    declared = length.decode("latin-1")
    if not (declared.isascii() and declared.isdigit()):
        return InvalidEnvelopeError("invalid content-length")
    digits = declared.lstrip("0")
    if len(digits) > len(str(limit)) or (digits and int(digits) > limit):
        return PayloadTooLargeError(f"body larger than {limit} bytes")
    return None


async def _body(receive: Receive, limit: int) -> bytes | ReplayAttackError:
    """The request body, or its typed refusal (too large, client disconnected)."""
    chunks: list[bytes] = []
    size = 0
    while True:
        message = await receive()
        kind = message["type"]
        if kind == "http.disconnect":
            return InvalidEnvelopeError("client disconnected")
        if kind != "http.request":
            continue
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > limit:
            return PayloadTooLargeError(f"body larger than {limit} bytes")
        chunks.append(chunk)
        if not message.get("more_body", False):
            return b"".join(chunks)


class Workers:
    """The threads that parse, read the store and check signatures for the event loop.

    A few suffice: nobody waits for a commit in them (the loop awaits those), and the
    signature check releases the GIL; a crowd of threads would only fight over it.  A
    result goes back as one ``call_soon_threadsafe`` into the caller's asyncio future,
    without ``concurrent.futures`` in between (its per-call futures and locks cost the
    loop more than the hand-off itself)."""

    def __init__(self, count: int) -> None:
        self._queue: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()
        self._threads = [
            threading.Thread(target=self._serve, name=f"antireplay-receive-{i}", daemon=True)
            for i in range(count)
        ]
        for thread in self._threads:
            thread.start()

    def __call__(self, fn: Callable[..., Any], *args: Any) -> asyncio.Future[Any]:
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        self._queue.put((loop, future, fn, args))
        return future

    def _serve(self) -> None:
        while (job := self._queue.get()) is not None:
            loop, future, fn, args = job
            try:
                result, error = fn(*args), None
            except BaseException as exc:  # delivered to the awaiting request, raised there
                result, error = None, exc
            with contextlib.suppress(RuntimeError):  # a closed loop has nobody left to answer
                loop.call_soon_threadsafe(_resolve, future, result, error)

    def shutdown(self) -> None:
        for _ in self._threads:
            self._queue.put(None)
        for thread in self._threads:
            thread.join(timeout=30)


_Job = tuple[asyncio.AbstractEventLoop, "asyncio.Future[Any]", Callable[..., Any], tuple[Any, ...]]


def _resolve(future: asyncio.Future[Any], result: Any, error: BaseException | None) -> None:
    if future.done():  # cancelled: the client went away
        return
    if error is None:
        future.set_result(result)
    else:
        future.set_exception(error)


def readiness(receiver: Receiver) -> str | None:
    """Why the gateway cannot serve commands now (store or audit trail), ``None`` if it can.

    Blocking I/O (run it in a thread); records nothing."""
    try:
        receiver.cache.store.ready()
    except Exception as exc:  # any backend's failure is the reason, never a 500
        return f"store: {exc}"
    return None if receiver.audit is None else audit_problem(receiver.audit)


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


def create_app(config: AppConfig, *, clock: Clock | None = None) -> Starlette:
    """The gateway application for ``config``."""
    receiver = build_receiver(config, clock)
    receiver.answer_wait_s = config.upstream_timeout_s  # a retry waits for its original
    upstream = resolve_upstream(config.upstream, config.upstream_timeout_s)
    metrics = Metrics(receiver)
    limit = config.max_body_bytes
    ticker = resolve(None)
    nack_type = config.security.nack_type
    workers = Workers(4)

    async def refuse(send: Send, error: ReplayAttackError) -> None:
        """Transport-level refusals: the same NACK as the pipeline's, with the configured type;
        the code decides the status (``errors.HTTP_STATUS``), as everywhere; counted like
        every rejection."""
        metrics.rejected.labels(str(error.code)).inc()
        await _answer(send, error.http_status, error.to_nack(None, nack_type=nack_type))

    async def messages(
        scope: Scope, receive: Receive, send: Send, ctype: bytes | None, length: bytes | None
    ) -> None:
        refusal = _framing_refusal(ctype, length, limit)
        if refusal is not None:
            return await refuse(send, refusal)
        raw = await _body(receive, limit)
        if not isinstance(raw, bytes):
            return await refuse(send, raw)
        started = ticker.monotonic()
        headers = {k.decode("latin-1"): v.decode("latin-1") for k, v in scope["headers"][::-1]}
        pending = await receiver.receive_async(raw, headers, workers)
        outcome = await _settle(receiver, workers, pending)
        metrics.observe(outcome, ticker.monotonic() - started)
        if outcome.retry is not None:  # a QoS retransmission: the original answer, marked
            return await _answer(send, outcome.retry.status, outcome.retry.body, outcome.retry)
        if not outcome.accepted:
            return await _answer(send, outcome.status, outcome.nack)
        status, answer = await _forward(upstream, outcome, metrics, nack_type)
        body = _encode_json(answer)
        receiver.hold_answer(outcome, status, (), body)  # for its QoS retransmissions
        return await _answer(send, status, body)

    async def healthz(_: Request) -> Response:
        return JSONResponse({"status": "ok", "time": time.time()})

    async def readyz(_: Request) -> Response:
        reason = await run_in_threadpool(readiness, receiver)
        if reason is not None:
            return JSONResponse({"status": "unavailable", "reason": reason}, status_code=503)
        return JSONResponse({"status": "ready"})

    async def metrics_endpoint(_: Request) -> Response:
        body = await run_in_threadpool(generate_latest, metrics.registry)  # may read the store
        return Response(body, media_type="text/plain; version=0.0.4")

    async def wrong_method(_: Request) -> Response:
        return Response(status_code=405)  # POST is answered by RefuseAmbiguousFraming

    @asynccontextmanager
    async def lifespan(_: Starlette) -> AsyncIterator[None]:
        yield
        workers.shutdown()
        if receiver.audit is not None:
            receiver.audit.close()

    app = Starlette(
        routes=[
            Route("/v1/messages", wrong_method, methods=["POST"]),
            Route("/healthz", healthz, methods=["GET"]),
            Route("/readyz", readyz, methods=["GET"]),
            Route("/metrics", metrics_endpoint, methods=["GET"]),
            *status_routes(receiver, metrics.registry, readiness),  # GET /, GET /status.json
        ],
        lifespan=lifespan,
        middleware=[Middleware(RefuseAmbiguousFraming, messages=messages, nack_type=nack_type)],
    )
    app.state.receiver = receiver
    app.state.metrics = metrics
    return app
