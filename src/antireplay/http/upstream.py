"""Forwarding an accepted message upstream, and the answer the client gets for it.

An upstream is named by a string (:func:`resolve_upstream`): ``http(s)://…`` is POSTed the
verified envelope (its canonical re-encoding, never the client's bytes) over httpx, in a
request of the gateway's own whose only other content is the verified signer in
``SIGNER_HEADERS``; ``module:function`` is called in a thread with the envelope (and the
:class:`~antireplay.rcan.auth.Signer` when its second parameter asks for it); none means
the gateway answers itself.  :class:`Forward` is the gateway's ``POST /v1/messages`` behind
its guard: the COMMAND_ACK with the upstream's result, or a COMMAND_NACK
``UPSTREAM_FAILED``.  The msg_id stays spent either way (the commit came first).  A call
that failed, timed out (the whole call is bounded) or answered what is not JSON is a 502;
an upstream that answered >= 400 gives its own status, ``delivered: "yes"`` and its body
in ``result``.  Each failure is counted and audited, durable before it is answered.
"""

from __future__ import annotations

import asyncio
import importlib
import inspect
from collections.abc import Awaitable, Callable
from typing import Any, Literal

import httpx
from starlette.concurrency import run_in_threadpool
from starlette.types import Receive, Scope, Send

from antireplay.core.errors import ConfigError, UpstreamFailedError
from antireplay.http.guard import Verified, answer, encode_json
from antireplay.http.metrics import Metrics
from antireplay.http.middleware import OUTCOME
from antireplay.rcan.auth import Signer
from antireplay.rcan.receive import Outcome, Receiver

Upstream = Callable[[Verified], Awaitable[tuple[int, Any]]]
#: An HTTP upstream's answer without a body (1xx, 204, 304): the client gets 200 and the ACK.
_NO_BODY = object()


def resolve_upstream(spec: str | None, timeout_s: float) -> Upstream | None:
    """``http(s)://…`` → POST via httpx, the signer in ``SIGNER_HEADERS``; ``module:function``
    → call it with the envelope (and the :class:`Signer` if its second parameter is named
    ``signer`` or annotated :class:`Signer`); None → answer locally.  The result is
    ``(status, body)``; ``_NO_BODY`` is an HTTP answer without a body (1xx, 204, 304).
    :func:`forward` bounds the whole call by ``timeout_s``."""
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
    with_signer = takes_signer(func)

    async def call(verified: Verified) -> tuple[int, Any]:
        if with_signer:
            return 200, await run_in_threadpool(func, verified.envelope, verified.signer)
        return 200, await run_in_threadpool(func, verified.envelope)

    return call


def takes_signer(func: Callable[..., Any]) -> bool:
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


async def forward(
    upstream: Upstream | None, verified: Verified, nack_type: int, timeout_s: float
) -> tuple[int, bytes, UpstreamFailedError | None]:
    """The answer to an accepted message (status, JSON bytes): its COMMAND_ACK (readable by
    the rcan SDK) with the upstream's result, or a COMMAND_NACK ``UPSTREAM_FAILED`` (the
    msg_id stays spent: README "Threat model"): 502 when the call failed, timed out (the
    whole call, ``timeout_s``) or its result is not JSON; the upstream's own status when it
    answered >= 400 (``delivered: "yes"``, its body in ``result``)."""
    ack = verified.ack
    if upstream is None:
        return 200, encode_json(ack), None
    try:
        status, result = await asyncio.wait_for(upstream(verified), timeout_s)
        if status >= 400:
            error = UpstreamFailedError(f"HTTP {status}", delivered="yes")
            nack = error.to_nack(verified.msg_id, nack_type=nack_type)
            relayed = None if result is _NO_BODY else result
            body = encode_json({**nack, "upstream_status": status, "result": relayed})
            return status, body, error
        if result is _NO_BODY:  # 1xx/204/304: nothing to relay but that it answered
            return 200, encode_json({**ack, "upstream_status": status}), None
        return status, encode_json({**ack, "result": result}), None
    except Exception as exc:
        error = UpstreamFailedError(type(exc).__name__, delivered=_delivered(exc))
        return 502, encode_json(error.to_nack(verified.msg_id, nack_type=nack_type)), error


def _delivered(exc: Exception) -> Literal["no", "unknown"]:
    """Whether a failed upstream call reached the upstream: ``"no"`` when no connection was
    made (nothing was sent), else ``"unknown"`` (sent, then failed, timed out, or answered
    what cannot be encoded)."""
    unsent = (httpx.ConnectError, httpx.ConnectTimeout, httpx.PoolTimeout)
    return "no" if isinstance(exc, unsent) else "unknown"


class Forward:
    """The gateway's ``POST /v1/messages`` behind its guard (a raw ASGI app: no Request
    object): the upstream's answer with the ACK, or the ACK alone; an upstream failure is
    counted and audited (durable before it is answered)."""

    def __init__(
        self, upstream: Upstream | None, metrics: Metrics, receiver: Receiver, timeout_s: float
    ) -> None:
        self.upstream, self.metrics, self.receiver = upstream, metrics, receiver
        self.timeout_s = timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        verified: Verified = scope["state"]["antireplay"]
        nack_type = self.receiver.config.nack_type
        status, body, failure = await forward(self.upstream, verified, nack_type, self.timeout_s)
        if failure is not None:
            self.metrics.upstream_errors.inc()
            outcome: Outcome = scope["state"][OUTCOME]
            await self.receiver.record_upstream_failure(outcome, failure)
        await answer(send, status, body)
