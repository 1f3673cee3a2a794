"""The HTTP gateway: a thin Starlette adapter in front of a robot's command API.

``POST /v1/messages`` takes one RCAN envelope (``application/json``, at most
``max_body_bytes``), runs :class:`~antireplay.rcan.receive.Receiver` (built from the
configuration by :func:`antireplay.wiring.build_receiver`), and either
forwards the accepted message upstream (the canonical re-encoding, never the
raw bytes) and answers with the upstream's result, or answers with the
COMMAND_NACK and its HTTP status.  ``GET /healthz`` (liveness: the process
answers), ``GET /`` and ``GET /status.json`` (the read-only status page,
:mod:`antireplay.http.status`), ``GET /readyz`` (readiness: the replay store could take a commit and
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

The request path is :class:`Guard`, an ASGI middleware, and the gateway is a
Guard around a small app that forwards what it verified: the same code serves
any Starlette/FastAPI robot API in process (:class:`Guard`, or
:class:`RcanGuard` as a FastAPI dependency), with the same answers, metrics
and audit trail.  The application gets a :class:`Verified` (envelope, signer,
ACK); an HTTP upstream gets the signer in headers the gateway sets itself
(``SIGNER_HEADERS``).  A refusal is answered by the Guard (no routing, no
Request object), and a request holds a thread only while there is work for
one: a byte-identical replay is refused on the event loop; parsing, the store
read and the signature run in a few :class:`Workers`; the state commit and the
audit row are group-committed and awaited on the loop
(:meth:`~antireplay.rcan.receive.Receiver.receive_async`).

With no configuration the gateway runs on the embedded default: SQLite state
and audit under ``./.antireplay/`` and a generated demo key pair
(:func:`embedded_default`).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import importlib
import inspect
import queue
import sqlite3
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterable, Iterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import httpx
import msgspec
from cryptography.hazmat.primitives.asymmetric import ed25519
from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from starlette._utils import get_route_path
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException
from starlette.middleware import Middleware
from starlette.requests import ClientDisconnect, Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from antireplay.audit import AuditLog, sanitize
from antireplay.config import AppConfig, KeyConfig
from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import (
    ConfigError,
    InvalidEnvelopeError,
    PayloadTooLargeError,
    ReplayAttackError,
    StateUnavailableError,
    UnsupportedMediaTypeError,
    UpstreamFailedError,
)
from antireplay.http.status import routes as status_routes
from antireplay.rcan.answers import MAX_BODY, HeldAnswer
from antireplay.rcan.auth import Signer, write_key_pair
from antireplay.rcan.envelope import encode
from antireplay.rcan.receive import Outcome, Receiver
from antireplay.state.groupcommit import GroupCommitter
from antireplay.wiring import build_receiver

DEMO_KID = "demo-operator"
#: Latency buckets from 50 µs (a check takes ~0.1 ms; an fsync a few ms) to 2.5 s.
LATENCY_BUCKETS = (
    0.00005, 0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5,
    1.0, 2.5, float("inf"),
)  # fmt: skip
_encode_json = msgspec.json.Encoder().encode
#: ``scope["state"]`` key of the accepted message's :class:`Outcome` (its audit context).
_OUTCOME = "antireplay.outcome"
_decode_json = msgspec.json.decode
#: Request headers only the guard sets (the verified signer); a client's copies are dropped.
SIGNER_HEADERS = ("rcan-signer-owner", "rcan-signer-kid", "rcan-signer-scopes", "rcan-msg-id")
_SIGNER_HEADERS = frozenset(name.encode() for name in SIGNER_HEADERS)
#: Response headers a held answer does not keep (per connection, or recomputed on resend).
_HOP_BY_HOP = frozenset({
    b"connection", b"keep-alive", b"proxy-authenticate", b"proxy-authorization", b"te",
    b"trailer", b"transfer-encoding", b"upgrade", b"content-length",
})  # fmt: skip
#: How much longer than the upstream budget a QoS retry waits for its original's answer.
ANSWER_SLACK_S = 1.0


@dataclass(frozen=True, slots=True)
class Verified:
    """What the guard hands the application with an accepted message: the envelope as
    verified (its canonical re-encoding, unsigned SDK hints removed), who signed it, and
    the COMMAND_ACK the gateway would answer."""

    envelope: dict[str, Any]
    signer: Signer
    msg_id: str | None
    warning: str | None
    ack: dict[str, Any]

    def headers(self) -> list[tuple[str, str]]:
        """The signer as request headers (``SIGNER_HEADERS``), every value sanitized."""
        owner, kid, scopes = _signer_values(self.signer)
        return [
            *zip(SIGNER_HEADERS, (owner, kid, scopes), strict=False),
            (SIGNER_HEADERS[3], self.msg_id or ""),
        ]


@functools.lru_cache(maxsize=256)
def _signer_values(signer: Signer) -> tuple[str, str, str]:
    """Owner, kid and sorted scopes, sanitized (a few keys sign everything: cached)."""
    scopes = ",".join(sorted(sanitize(scope) or "" for scope in signer.scopes))
    return sanitize(signer.owner) or "", sanitize(signer.kid) or "", scopes


Upstream = Callable[[Verified], Awaitable[tuple[int, Any]]]


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
    """``http(s)://…`` → POST via httpx, the signer in ``SIGNER_HEADERS``; ``module:function``
    → call it with the envelope (and the :class:`Signer` if its second parameter is named
    ``signer`` or annotated :class:`Signer`); None → answer locally.  The result is
    ``(status, body)``; ``_NO_BODY`` is an HTTP answer without a body (1xx, 204, 304).
    :func:`_forward` bounds the whole call by ``upstream_timeout_s``."""
    if spec is None:
        return None
    if spec.startswith(("http://", "https://")):
        client = httpx.AsyncClient(timeout=timeout_s)

        async def post(verified: Verified) -> tuple[int, Any]:
            # A request of our own: nothing the client sent but the verified envelope.
            reply = await client.post(spec, json=verified.envelope, headers=verified.headers())
            if not reply.content:
                return reply.status_code, _NO_BODY
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
    with_signer = _takes_two(func)

    async def call(verified: Verified) -> tuple[int, Any]:
        if with_signer:
            return 200, await run_in_threadpool(func, verified.envelope, verified.signer)
        return 200, await run_in_threadpool(func, verified.envelope)

    return call


#: An HTTP upstream's answer without a body (1xx, 204, 304): the client gets 200 and the ACK.
_NO_BODY = object()


def _takes_two(func: Callable[..., Any]) -> bool:
    """Whether ``func`` takes the :class:`Signer` second: its second positional parameter is
    named ``signer`` or annotated ``Signer`` (``handle(envelope, retries=3)`` is not)."""
    try:
        params = list(inspect.signature(func).parameters.values())
    except (TypeError, ValueError):  # no signature to read: called as before
        return False
    positional = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    second = [p for p in params if p.kind in positional][1:2]
    if not second:
        return False
    annotation = second[0].annotation
    named = annotation is Signer or (
        isinstance(annotation, str) and annotation.rsplit(".", 1)[-1] == "Signer"
    )
    return second[0].name == "signer" or named


async def _forward(
    upstream: Upstream | None, verified: Verified, nack_type: int, timeout_s: float
) -> tuple[int, bytes, UpstreamFailedError | None]:
    """The answer to an accepted message (status, JSON bytes): its COMMAND_ACK (readable by
    the rcan SDK) with the upstream's result, or a COMMAND_NACK ``UPSTREAM_FAILED`` (the
    msg_id stays spent: README "Threat model"): 502 when the call failed, timed out (the
    whole call, ``timeout_s``) or its result is not JSON; the upstream's own status when it
    answered >= 400 (``delivered: "yes"``, its body in ``result``)."""
    answer = verified.ack
    if upstream is None:
        return 200, _encode_json(answer), None
    try:
        status, result = await asyncio.wait_for(upstream(verified), timeout_s)
        if status >= 400:
            error = UpstreamFailedError(f"HTTP {status}", delivered="yes")
            nack = error.to_nack(verified.msg_id, nack_type=nack_type)
            relayed = None if result is _NO_BODY else result
            body = _encode_json({**nack, "upstream_status": status, "result": relayed})
            return status, body, error
        if result is _NO_BODY:  # 1xx/204/304: nothing to relay but that it answered
            return 200, _encode_json({**answer, "upstream_status": status}), None
        return status, _encode_json({**answer, "result": result}), None
    except Exception as exc:
        error = UpstreamFailedError(type(exc).__name__, delivered=_delivered(exc))
        return 502, _encode_json(error.to_nack(verified.msg_id, nack_type=nack_type)), error


def _delivered(exc: Exception) -> Literal["no", "unknown"]:
    """Whether a failed upstream call reached the upstream: ``"no"`` when no connection was
    made (nothing was sent), else ``"unknown"`` (sent, then failed, timed out, or answered
    what cannot be encoded)."""
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

    async def endpoint(self, _: Request) -> Response:
        """``GET /metrics`` (a Starlette endpoint: ``app.add_route("/metrics", ...)``)."""
        body = await run_in_threadpool(generate_latest, self.registry)  # may read the store
        return Response(body, media_type="text/plain; version=0.0.4")

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
        stats = self.receiver.stats
        held = CounterMetricFamily(
            "antireplay_estops_unaudited", "ESTOPs delivered while the audit trail failed"
        )
        held.add_metric([], stats.held_estops)
        yield held
        dropped = CounterMetricFamily(
            "antireplay_audit_held_dropped", "Held ESTOP audit rows dropped (bound reached)"
        )
        dropped.add_metric([], stats.held_dropped)
        yield dropped
        waiting = GaugeMetricFamily(
            "antireplay_audit_held_rows", "ESTOP audit rows held until the trail is writable"
        )
        waiting.add_metric([], self.receiver.held_rows)
        yield waiting


class Refused(HTTPException):
    """A refusal: the COMMAND_NACK and its HTTP status, exactly as the gateway answers them.
    :class:`RcanGuard` raises it; the handler :meth:`RcanGuard.install` adds answers it
    with the NACK as the body.  An HTTPException (``detail``: the NACK's JSON text), so
    without that handler Starlette's or FastAPI's still answers with the typed status."""

    def __init__(
        self, status: int, nack: dict[str, Any] | bytes, *, close: bool = False,
        held: HeldAnswer | None = None,
    ) -> None:  # fmt: skip
        body = nack if isinstance(nack, bytes) else _encode_json(nack)
        super().__init__(status, body.decode("utf-8", "replace"))
        self.status, self.nack, self.close, self.held = status, nack, close, held
        self.body = body

    @classmethod
    def retry(cls, held: HeldAnswer) -> Refused:
        """A QoS retransmission: the original answer again, marked, never a second run."""
        return cls(held.status, held.body, held=held)

    async def answer(self, send: Send) -> None:
        await _answer(send, self.status, self.nack, self.held, close=self.close)

    def response(self) -> Response:
        if self.held is None:
            headers = {"connection": "close"} if self.close else {}
            return Response(self.body, self.status, headers=headers, media_type="application/json")
        response = Response(self.body, self.status)
        response.raw_headers = [
            *_held_headers(self.held),
            (b"content-length", b"%d" % len(self.body)),
        ]
        return response


Framing = tuple[bytes | None, bytes | None, bool]


class _Checkpoint:
    """The gateway's request path for one POST, shared by :class:`Guard` (ASGI middleware,
    and the gateway itself) and :class:`RcanGuard` (FastAPI dependency): framing refusals,
    the body limit, :meth:`Receiver.receive_async`, metrics."""

    def __init__(
        self,
        config: AppConfig | None,
        *,
        clock: Clock | None,
        receiver: Receiver | None,
        metrics: Metrics | None,
    ) -> None:
        self._owns_receiver = receiver is None
        if receiver is None:
            receiver = build_receiver(config if config is not None else embedded_default(), clock)
        self.receiver = receiver
        self.metrics = metrics if metrics is not None else Metrics(receiver)
        self.limit = receiver.max_bytes
        self.nack_type = receiver.config.nack_type
        self.workers = Workers(4)
        self._ticker = resolve(None)
        self._closed = False

    @property
    def metrics_endpoint(self) -> Callable[[Request], Awaitable[Response]]:
        """A Starlette endpoint serving these metrics: ``app.add_route("/metrics", ...)``."""
        return self.metrics.endpoint

    def close(self) -> None:
        """Stop the worker threads (and close the audit trail of a receiver built here)."""
        if self._closed:
            return
        self._closed = True
        self.workers.shutdown()
        if self._owns_receiver and self.receiver.audit is not None:
            self.receiver.audit.close()

    def ambiguous(self, framing: Framing) -> Refused | None:
        """Both Content-Length and Transfer-Encoding: refused and closed (RFC 9112)."""
        if framing[1] is None or not framing[2]:
            return None
        reason = "both Content-Length and Transfer-Encoding (RFC 9112 section 6.1)"
        nack = InvalidEnvelopeError(reason).to_nack(None, nack_type=self.nack_type)
        return Refused(400, nack, close=True)

    async def check(
        self, scope: Scope, receive: Receive, framing: Framing
    ) -> tuple[Verified, bytes, Outcome] | Refused:
        """One POSTed envelope: its :class:`Verified`, canonical bytes and outcome, or its
        refusal (a QoS retransmission's: the original answer, :meth:`Refused.retry`)."""
        refusal = _framing_refusal(framing[0], framing[1], self.limit)
        raw = await _body(receive, self.limit) if refusal is None else refusal
        if not isinstance(raw, bytes):
            # Transport-level refusals: the same NACK as the pipeline's, with the configured
            # type; the code decides the status (errors.HTTP_STATUS); counted like the rest.
            self.metrics.rejected.labels(str(raw.code)).inc()
            return Refused(raw.http_status, raw.to_nack(None, nack_type=self.nack_type))
        started = self._ticker.monotonic()
        headers = {k.decode("latin-1"): v.decode("latin-1") for k, v in scope["headers"][::-1]}
        outcome = await self.receiver.receive_async(raw, headers, self.workers)
        self.metrics.observe(outcome, self._ticker.monotonic() - started)
        if outcome.retry is not None:
            return Refused.retry(outcome.retry)
        nack = outcome.nack
        if nack is not None:
            return Refused(outcome.status, nack)
        assert outcome.envelope is not None and outcome.signer is not None
        body = encode(outcome.envelope)
        ack = outcome.ack or {}  # COMMAND_ACK: readable by the rcan SDK
        verified = Verified(
            _decode_json(body), outcome.signer, outcome.msg_id, outcome.warning, ack
        )
        return verified, body, outcome


class Guard(_Checkpoint):
    """ASGI middleware that runs the gateway's request path inside an application.

    ``POST`` on one of ``paths`` is checked exactly as ``antireplay serve`` checks it (the
    gateway *is* a Guard around its forwarding app): a refusal is answered here with the
    gateway's NACK and status; an accepted message reaches ``app`` with the canonical
    envelope as its body, the verified signer in ``SIGNER_HEADERS`` and
    ``scope["state"]["antireplay"]``: a :class:`Verified` (Starlette:
    ``request.state.antireplay``); another method on those paths is refused (405), and so
    is a WebSocket (:func:`_refuse_websocket`).  A client's ``SIGNER_HEADERS`` are dropped
    from every request (HTTP and WebSocket), on every route, and so is
    every request with both Content-Length and Transfer-Encoding (refused and closed: the
    request-smuggling shape).  The app's answer passes through as it is sent (streaming
    works); a copy is kept only for a message a QoS retransmission may repeat.  The hot
    path builds no Request object.  Lifespan shutdown stops its workers."""

    def __init__(
        self,
        app: ASGIApp,
        config: AppConfig | None = None,
        *,
        paths: tuple[str, ...] = ("/v1/messages",),
        clock: Clock | None = None,
        receiver: Receiver | None = None,
        metrics: Metrics | None = None,
        accepted: ASGIApp | None = None,
    ) -> None:
        super().__init__(config, clock=clock, receiver=receiver, metrics=metrics)
        self.app = app
        self.paths = frozenset(paths)
        #: Where an accepted message goes (default ``app``; the gateway: its forwarder).
        self.accepted = app if accepted is None else accepted

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "lifespan":
            return await self.app(scope, receive, self._closing(send))
        if scope["type"] != "http":
            return await self._not_http(scope, receive, send)
        framing = _framing(scope)
        refused = self.ambiguous(framing)
        if refused is not None:
            return await refused.answer(send)
        scope = _unclaimed(scope)
        if _route_path(scope) not in self.paths:
            return await self.app(scope, receive, send)
        if scope["method"] != "POST":
            return await self._not_post().answer(send)
        result = await self.check(scope, receive, framing)
        if isinstance(result, Refused):
            return await result.answer(send)
        verified, body, outcome = result
        inner = {
            **scope,
            "headers": _verified_headers(scope["headers"], verified, len(body)),
            "state": {**scope.get("state", {}), "antireplay": verified, _OUTCOME: outcome},
        }
        relay, finish = self._holding(outcome, send)
        try:
            await self.accepted(inner, _replay(body, receive), relay)
        finally:
            finish()

    async def _not_http(self, scope: Scope, receive: Receive, send: Send) -> None:
        """A WebSocket (or any other connection but HTTP and lifespan): a client's
        ``SIGNER_HEADERS`` dropped on every route, and refused before the app on a guarded
        path, where only a POSTed envelope is checked."""
        scope = _unclaimed(scope)
        if "path" in scope and _route_path(scope) not in self.paths:
            return await self.app(scope, receive, send)
        if scope["type"] == "websocket":
            await _refuse_websocket(scope, receive, send, self._not_post())

    def _not_post(self) -> Refused:
        nack = InvalidEnvelopeError("method must be POST").to_nack(None, nack_type=self.nack_type)
        return Refused(405, nack)

    def _holding(self, outcome: Outcome, send: Send) -> tuple[Send, Callable[[], None]]:
        """``send`` passing the answer through as it comes, and copying it (at most
        ``MAX_BODY`` bytes) only when a QoS retransmission may ask for it (the memo has
        this message in flight: it declared qos >= 1 when received).  A complete answer is
        held as the final body message passes; a stream cut short, an app that raised or
        an answer too large drops the entry (its waiters get 409 at once)."""
        env = outcome.envelope
        msg_id = env.msg_id if env is not None and type(env.msg_id) is str else None
        if msg_id is None or not self.receiver.answers.in_flight(msg_id):
            return send, _nothing
        answers = self.receiver.answers
        start: Message | None = None
        chunks: list[bytes] = []
        size = 0
        copying, complete = True, False

        async def holding(message: Message) -> None:
            nonlocal start, size, copying, complete
            if message["type"] == "http.response.start":
                start = message
            elif message["type"] == "http.response.body" and copying:
                chunk = message.get("body", b"")
                size += len(chunk)
                if size > MAX_BODY:  # not held: a retry gets 409
                    copying = False
                    chunks.clear()
                    answers.drop(msg_id)
                else:
                    chunks.append(chunk)
                if copying and start is not None and not message.get("more_body", False):
                    complete = True
                    headers = [
                        (k.decode("latin-1"), v.decode("latin-1"))
                        for k, v in start.get("headers", ())
                        if k.lower() not in _HOP_BY_HOP
                    ]
                    self.receiver.hold_answer(outcome, start["status"], headers, b"".join(chunks))
            await send(message)

        def finish() -> None:
            if not complete:
                answers.drop(msg_id)

        return holding, finish

    def _closing(self, send: Send) -> Send:
        async def closing(message: Message) -> None:
            if message["type"] in {"lifespan.shutdown.complete", "lifespan.shutdown.failed"}:
                await run_in_threadpool(self.close)
            await send(message)

        return closing


class RcanGuard(_Checkpoint):
    """The gateway's request path as a FastAPI dependency: ``Depends(guard)`` reads the
    body, runs it and returns the :class:`Verified` message; a refusal raises
    :class:`Refused`, answered with the gateway's exact NACK and status by the handler
    :meth:`install` adds.  FastAPI is not imported here: any Starlette request works."""

    def __init__(
        self,
        config: AppConfig | None = None,
        *,
        clock: Clock | None = None,
        receiver: Receiver | None = None,
    ) -> None:
        super().__init__(config, clock=clock, receiver=receiver, metrics=None)

    async def __call__(self, request: Request) -> Verified:
        framing = _framing(request.scope)
        result = self.ambiguous(framing) or await self.check(
            request.scope, _streamed(request), framing
        )
        if isinstance(result, Refused):
            raise result
        verified, _, outcome = result
        if outcome.envelope is not None and type(outcome.envelope.msg_id) is str:
            # The route's answer is not seen here: a QoS retransmission is refused (409),
            # never run again, rather than kept waiting for an answer nobody holds.
            self.receiver.answers.drop(outcome.envelope.msg_id)
        _speak_for_signer(request.scope, verified)
        return verified

    def install(self, app: Starlette) -> None:
        """Answer :class:`Refused` with the NACK itself (not wrapped in ``detail``), and drop
        a client's ``SIGNER_HEADERS`` from every request (HTTP and WebSocket), on every
        route (call it before the app starts)."""
        app.add_exception_handler(Refused, _refused_response)
        app.add_middleware(_Unclaimed)


class _Unclaimed:
    """ASGI layer of :meth:`RcanGuard.install`: only the guard speaks for the signer."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        await self.app(_unclaimed(scope), receive, send)


def _unclaimed(scope: Scope) -> Scope:
    """``scope`` without a client's ``SIGNER_HEADERS`` (the same scope if it has none)."""
    headers = scope.get("headers")
    if headers is None or not any(name.lower() in _SIGNER_HEADERS for name, _ in headers):
        return scope
    return {**scope, "headers": _without_signer(headers)}


def _without_signer(headers: Iterable[tuple[bytes, bytes]]) -> list[tuple[bytes, bytes]]:
    return [(name, value) for name, value in headers if name.lower() not in _SIGNER_HEADERS]


def _signer_pairs(verified: Verified) -> list[tuple[bytes, bytes]]:
    return [(name.encode(), value.encode()) for name, value in verified.headers()]


def _speak_for_signer(scope: Scope, verified: Verified) -> None:
    """The route's request headers carry the verified signer, never a client's claim: the
    header list is rewritten in place, so a ``Headers`` already read from it sees it too."""
    rewritten = [*_without_signer(scope["headers"]), *_signer_pairs(verified)]
    if isinstance(scope["headers"], list):
        scope["headers"][:] = rewritten
    else:
        scope["headers"] = rewritten


async def _refuse_websocket(scope: Scope, receive: Receive, send: Send, refusal: Refused) -> None:
    """Refuse a WebSocket handshake: ``refusal`` as an HTTP answer where the server offers
    denial responses, else a close before accepting (1008, policy violation; HTTP 403)."""
    if (await receive())["type"] != "websocket.connect":
        return  # the client is gone
    if "websocket.http.response" in (scope.get("extensions") or {}):

        async def denial(message: Message) -> None:
            await send({**message, "type": f"websocket.{message['type']}"})

        return await refusal.answer(denial)
    await send({"type": "websocket.close", "code": 1008, "reason": "method must be POST"})


async def _refused_response(_: Request, exc: Exception) -> Response:
    assert isinstance(exc, Refused)
    return exc.response()


def _framing(scope: Scope) -> Framing:
    """The first Content-Type and Content-Length, and whether Transfer-Encoding is present."""
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
    return ctype, length, chunked


def _verified_headers(
    headers: list[tuple[bytes, bytes]], verified: Verified, length: int
) -> list[tuple[bytes, bytes]]:
    """The request headers for the application: the new body's length, the signer's."""
    dropped = {b"content-length", b"transfer-encoding", *_SIGNER_HEADERS}
    kept = [(name, value) for name, value in headers if name.lower() not in dropped]
    return [*kept, (b"content-length", b"%d" % length), *_signer_pairs(verified)]


def _nothing() -> None:
    """Nothing to settle: the message's answer is not kept."""


def _replay(body: bytes, receive: Receive) -> Receive:
    """The application's ``receive``: the canonical body once, then the client's messages."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if sent:
            return await receive()
        sent = True
        return {"type": "http.request", "body": body, "more_body": False}

    return replay


def _streamed(request: Request) -> Receive:
    """ASGI ``receive`` over ``request.stream()`` (which also replays a body already read)."""
    chunks = request.stream().__aiter__()

    async def receive() -> Message:
        try:
            chunk = await chunks.__anext__()
        except StopAsyncIteration:
            return {"type": "http.request", "body": b"", "more_body": False}
        except ClientDisconnect:
            return {"type": "http.disconnect"}
        return {"type": "http.request", "body": chunk, "more_body": True}

    return receive


def _route_path(scope: Scope) -> str:
    """The path the router would match: Starlette's own ``get_route_path``."""
    return get_route_path(scope)


def _held_headers(held: HeldAnswer) -> list[tuple[bytes, bytes]]:
    return [(k.encode("latin-1"), v.encode("latin-1")) for k, v in held.headers]


async def _answer(
    send: Send, status: int, content: object, held: HeldAnswer | None = None, *, close: bool = False
) -> None:
    """One response, sent as two ASGI messages (what JSONResponse sends, cheaper): JSON
    ``content`` (or its encoding as bytes), or a held answer's body under its own headers."""
    body = content if isinstance(content, bytes) else _encode_json(content)
    headers = _held_headers(held) if held else [(b"content-type", b"application/json")]
    headers.append((b"content-length", b"%d" % len(body)))
    if close:
        headers.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


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
    """The gateway application for ``config``: a :class:`Guard` in front of an app whose
    ``POST /v1/messages`` forwards what the guard verified (one code path by construction)."""
    receiver = build_receiver(config, clock)
    # A retry waits for its original while that is still within its upstream budget.
    receiver.answer_wait_s = config.upstream_timeout_s + ANSWER_SLACK_S
    metrics = Metrics(receiver)
    upstream = resolve_upstream(config.upstream, config.upstream_timeout_s)
    forward = _Forward(upstream, metrics, receiver, config.upstream_timeout_s)

    async def healthz(_: Request) -> Response:
        return JSONResponse({"status": "ok", "time": time.time()})

    async def readyz(_: Request) -> Response:
        reason = await run_in_threadpool(readiness, receiver)
        if reason is not None:
            return JSONResponse({"status": "unavailable", "reason": reason}, status_code=503)
        return JSONResponse({"status": "ready"})

    @asynccontextmanager
    async def lifespan(_: Starlette) -> AsyncIterator[None]:
        yield  # the Guard stops its workers once this has run
        if receiver.audit is not None:
            receiver.audit.close()

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
            Middleware(Guard, receiver=receiver, metrics=metrics, accepted=forward)
        ],  # an accepted message goes straight to the forwarder (no routing on the hot path)
    )
    app.state.receiver = receiver
    app.state.metrics = metrics
    return app


class _Forward:
    """The gateway's ``POST /v1/messages`` behind its :class:`Guard` (a raw ASGI app: no
    Request object): the upstream's answer with the ACK, or the ACK alone; an upstream
    failure is counted and audited (durable before it is answered)."""

    def __init__(
        self, upstream: Upstream | None, metrics: Metrics, receiver: Receiver, timeout_s: float
    ) -> None:
        self.upstream, self.metrics, self.receiver = upstream, metrics, receiver
        self.timeout_s = timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        verified: Verified = scope["state"]["antireplay"]
        nack_type = self.receiver.config.nack_type
        status, body, failure = await _forward(self.upstream, verified, nack_type, self.timeout_s)
        if failure is not None:
            self.metrics.upstream_errors.inc()
            outcome: Outcome = scope["state"][_OUTCOME]
            await self.receiver.record_upstream_failure(outcome, failure)
        await _answer(send, status, body)
