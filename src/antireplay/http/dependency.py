"""The guard as a FastAPI dependency, and the layer that keeps the signer headers its own.

``Depends(guard)`` reads the request body itself, runs
:meth:`~antireplay.http.guard.GuardBase.open` and returns the
:class:`~antireplay.http.guard.Verified` message; a refusal raises
:class:`~antireplay.http.guard.HttpRefusal`, which the handler :meth:`GuardDependency.install`
adds answers with the gateway's exact NACK and status.  The dependency does not see the
route's answer, so a QoS retransmission behind it is refused (409), never run again, rather
than kept waiting for an answer nobody holds.  The route's request headers carry the
verified signer (``SIGNER_HEADERS``), never a client's claim, and :class:`Unclaimed` (added
by ``install``) drops a client's copies from every HTTP and WebSocket request, on every
route.  FastAPI is not imported here: any Starlette request works.
"""

from __future__ import annotations

from starlette.applications import Starlette
from starlette.requests import ClientDisconnect, Request
from starlette.responses import Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from antireplay.http.guard import (
    GuardBase,
    HttpRefusal,
    Verified,
    framing,
    signer_pairs,
    unclaimed,
    without_signer,
)
from antireplay.rcan.receive import Receiver


class GuardDependency(GuardBase):
    """The gateway's request path on ``receiver`` as a FastAPI dependency."""

    def __init__(self, receiver: Receiver, *, owns_receiver: bool = False) -> None:
        super().__init__(receiver, owns_receiver=owns_receiver)

    async def __call__(self, request: Request) -> Verified:
        framed = framing(request.scope)
        result = self.ambiguous(framed) or await self.open(
            request.scope, _streamed(request), framed
        )
        if isinstance(result, HttpRefusal):
            raise result
        verified, outcome = result
        if outcome.envelope is not None and type(outcome.envelope.msg_id) is str:
            # The route's answer is not seen here: a QoS retransmission is refused (409),
            # never run again, rather than kept waiting for an answer nobody holds.
            self.receiver.answers.drop(outcome.envelope.msg_id)
        _speak_for_signer(request.scope, verified)
        return verified

    def install(self, app: Starlette) -> None:
        """Answer :class:`HttpRefusal` with the NACK itself (not wrapped in ``detail``), and drop
        a client's ``SIGNER_HEADERS`` from every request (HTTP and WebSocket), on every
        route (call it before the app starts)."""
        app.add_exception_handler(HttpRefusal, _refused_response)
        app.add_middleware(Unclaimed)


class Unclaimed:
    """ASGI layer of :meth:`GuardDependency.install`: only the guard speaks for the signer."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        await self.app(unclaimed(scope), receive, send)


def _speak_for_signer(scope: Scope, verified: Verified) -> None:
    """The route's request headers carry the verified signer, never a client's claim: the
    header list is rewritten in place, so a ``Headers`` already read from it sees it too."""
    rewritten = [*without_signer(scope["headers"]), *signer_pairs(verified)]
    if isinstance(scope["headers"], list):
        scope["headers"][:] = rewritten
    else:
        scope["headers"] = rewritten


async def _refused_response(_: Request, exc: Exception) -> Response:
    assert isinstance(exc, HttpRefusal)
    return exc.response()


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
