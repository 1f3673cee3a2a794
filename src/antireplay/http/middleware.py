"""The guard as ASGI middleware: the gateway's request path inside any ASGI application.

``POST`` on one of ``paths`` runs :meth:`~antireplay.http.guard.GuardBase.open` exactly as
``antireplay serve`` does (the gateway *is* this middleware around its forwarding app).  A
refusal is answered here with the gateway's NACK and status, before routing and without a
Request object.  An accepted message reaches the app (or ``accepted``, the gateway's
forwarder) with the canonical envelope as its body, the verified signer in
``SIGNER_HEADERS``, and ``scope["state"]["antireplay"]``: a
:class:`~antireplay.http.guard.Verified` (Starlette: ``request.state.antireplay``).

Every scope type is handled on every route: a client's ``SIGNER_HEADERS`` are dropped from
every HTTP and WebSocket request; a request with both Content-Length and
Transfer-Encoding is refused and closed on every route; another method on a guarded path is
refused (405), and so is a WebSocket handshake there (405 where the server offers denial
responses, else closed with 1008).  Lifespan passes through, and its shutdown stops the
guard's workers.

The app's answer passes through as it is sent (streaming works).  A copy is kept only for a
message a QoS retransmission may repeat (it is in flight in the answer memo), up to
``MAX_BODY`` bytes, and held once the final body message passes; an answer cut short, an app
that raised, or one too large drops the entry, so its waiters get 409 at once.
"""

from __future__ import annotations

from collections.abc import Callable

from starlette._utils import get_route_path
from starlette.concurrency import run_in_threadpool
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from antireplay.core.errors import InvalidEnvelopeError
from antireplay.http.guard import (
    SIGNER_HEADER_NAMES,
    GuardBase,
    HttpRefusal,
    Verified,
    encode_json,
    framing,
    signer_pairs,
    unclaimed,
)
from antireplay.http.metrics import Metrics
from antireplay.rcan.answers import MAX_BODY
from antireplay.rcan.receive import Outcome, Receiver

#: ``scope["state"]`` key of the accepted message's :class:`Outcome` (its audit context).
OUTCOME = "antireplay.outcome"
#: Response headers a held answer does not keep (per connection, or recomputed on resend).
_HOP_BY_HOP = frozenset({
    b"connection", b"keep-alive", b"proxy-authenticate", b"proxy-authorization", b"te",
    b"trailer", b"transfer-encoding", b"upgrade", b"content-length",
})  # fmt: skip


class GuardMiddleware(GuardBase):
    """ASGI middleware that runs the gateway's request path on ``receiver`` for ``paths``;
    an accepted message goes to ``accepted`` (default ``app``)."""

    def __init__(
        self,
        app: ASGIApp,
        receiver: Receiver,
        *,
        paths: tuple[str, ...] = ("/v1/messages",),
        metrics: Metrics | None = None,
        accepted: ASGIApp | None = None,
        owns_receiver: bool = False,
    ) -> None:
        super().__init__(receiver, metrics=metrics, owns_receiver=owns_receiver)
        self.app = app
        self.paths = frozenset(paths)
        #: Where an accepted message goes (default ``app``; the gateway: its forwarder).
        self.accepted = app if accepted is None else accepted

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "lifespan":
            return await self.app(scope, receive, self._closing(send))
        if scope["type"] != "http":
            return await self._not_http(scope, receive, send)
        framed = framing(scope)
        refused = self.ambiguous(framed)
        if refused is not None:
            return await refused.answer(send)
        scope = unclaimed(scope)
        if route_path(scope) not in self.paths:
            return await self.app(scope, receive, send)
        if scope["method"] != "POST":
            return await self._not_post().answer(send)
        try:  # an ESTOP holds the door until it is forwarded and answered
            result = await self.open(scope, receive, framed, hold=True)
            if isinstance(result, HttpRefusal):
                return await result.answer(send)
            verified, outcome = result
            body = encode_json(verified.envelope)
            inner = {
                **scope,
                "headers": _verified_headers(scope["headers"], verified, len(body)),
                "state": {**scope.get("state", {}), "antireplay": verified, OUTCOME: outcome},
            }
            relay, finish = self._holding(outcome, send)
            try:
                await self.accepted(inner, _replay(body, receive), relay)
            finally:
                finish()
        finally:
            self.let_go()

    async def _not_http(self, scope: Scope, receive: Receive, send: Send) -> None:
        """A WebSocket (or any other connection but HTTP and lifespan): a client's
        ``SIGNER_HEADERS`` dropped on every route, and refused before the app on a guarded
        path, where only a POSTed envelope is checked."""
        scope = unclaimed(scope)
        if "path" in scope and route_path(scope) not in self.paths:
            return await self.app(scope, receive, send)
        if scope["type"] == "websocket":
            await _refuse_websocket(scope, receive, send, self._not_post())

    def _not_post(self) -> HttpRefusal:
        nack = InvalidEnvelopeError("method must be POST").to_nack(None, nack_type=self.nack_type)
        return HttpRefusal(405, nack)

    def _holding(self, outcome: Outcome, send: Send) -> tuple[Send, Callable[[], None]]:
        """``send`` passing the answer through as it comes, and copying it (at most
        ``MAX_BODY`` bytes) only when a QoS retransmission may ask for it (the memo has
        this message in flight: it declared qos >= 1 when received)."""
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


def route_path(scope: Scope) -> str:
    """The path the router would match: Starlette's own ``get_route_path``."""
    return get_route_path(scope)


async def _refuse_websocket(
    scope: Scope, receive: Receive, send: Send, refusal: HttpRefusal
) -> None:
    """Refuse a WebSocket handshake: ``refusal`` as an HTTP answer where the server offers
    denial responses, else a close before accepting (1008, policy violation; HTTP 403)."""
    if (await receive())["type"] != "websocket.connect":
        return  # the client is gone
    if "websocket.http.response" in (scope.get("extensions") or {}):

        async def denial(message: Message) -> None:
            await send({**message, "type": f"websocket.{message['type']}"})

        return await refusal.answer(denial)
    await send({"type": "websocket.close", "code": 1008, "reason": "method must be POST"})


def _verified_headers(
    headers: list[tuple[bytes, bytes]], verified: Verified, length: int
) -> list[tuple[bytes, bytes]]:
    """The request headers for the application: the new body's length, the signer's."""
    dropped = {b"content-length", b"transfer-encoding", *SIGNER_HEADER_NAMES}
    kept = [(name, value) for name, value in headers if name.lower() not in dropped]
    return [*kept, (b"content-length", b"%d" % length), *signer_pairs(verified)]


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
