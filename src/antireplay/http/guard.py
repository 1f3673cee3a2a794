"""The guard: one POSTed envelope's request path, shared by the middleware and the dependency.

:class:`GuardBase` is what :class:`~antireplay.http.middleware.GuardMiddleware` (ASGI
middleware, and so the gateway itself) and :class:`~antireplay.http.dependency.GuardDependency`
(a FastAPI dependency) both run, so the two give the same answers, metrics and audit trail.
Transport framing comes first and records nothing: a request with both ``Content-Length``
and ``Transfer-Encoding`` is refused with 400 and the connection closed (RFC 9112 §6.1; a
proxy in front that honours the other header would see a different request boundary),
then a content type other than JSON (415), a declared or actual body over the limit (413)
or a client gone mid-body.  Those refusals are counted like the receiver's.  Then
:meth:`GuardBase.open` runs :meth:`~antireplay.rcan.receive.Receiver.receive_async`
(check -> authenticate -> commit; the signature in one job on a few
:class:`~antireplay.http.workers.Workers`, a fresh SAFETY message's in their urgent lane,
holding the :class:`~antireplay.http.workers.Door` that other requests wait at until its answer;
the commit and audit row awaited on the loop)
and observes the outcome.  An accepted message becomes a :class:`Verified` (the envelope
as verified, built once from the parsed envelope: its canonical re-encoding, with the
signature re-encoded from its decoded form); a refusal becomes :class:`HttpRefusal`, the
COMMAND_NACK and its HTTP status (a QoS retransmission's: the original answer again).

``SIGNER_HEADERS`` are the request headers only the guard sets (the verified signer); a
client's copies are dropped (:func:`unclaimed`).  :func:`answer` sends one response as two
ASGI messages, with no Response object on the hot path.
"""

from __future__ import annotations

import functools
from collections.abc import Awaitable, Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import msgspec
from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import Response
from starlette.types import Receive, Scope, Send

from antireplay.audit import sanitize
from antireplay.core.clock import resolve
from antireplay.core.errors import (
    InvalidEnvelopeError,
    PayloadTooLargeError,
    ReplayAttackError,
    UnsupportedMediaTypeError,
)
from antireplay.http.metrics import Metrics
from antireplay.http.readiness import ready_endpoint
from antireplay.http.workers import Door, Workers
from antireplay.rcan.answers import HeldAnswer
from antireplay.rcan.auth import Signer
from antireplay.rcan.envelope import Envelope
from antireplay.rcan.receive import Outcome, Receiver
from antireplay.rcan.steps import NeedsCommit

encode_json = msgspec.json.Encoder().encode
#: Request headers only the guard sets (the verified signer); a client's copies are dropped.
SIGNER_HEADERS = ("rcan-signer-owner", "rcan-signer-kid", "rcan-signer-scopes", "rcan-msg-id")
SIGNER_HEADER_NAMES = frozenset(name.encode() for name in SIGNER_HEADERS)
#: NACK bodies kept prebuilt at most (then forgotten all at once and built again).
PREBUILT = 4096


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


def as_forwarded(env: Envelope) -> dict[str, Any]:
    """The envelope as forwarded (what :func:`~antireplay.rcan.envelope.encode` writes), as
    JSON values: ``sig`` from its decoded form, never the raw bytes."""
    body: dict[str, Any] = msgspec.to_builtins(env, builtin_types=(msgspec.Raw,))
    sig = env.signature()
    if sig is None:
        body.pop("sig", None)
    else:
        body["sig"] = msgspec.to_builtins(sig)
    return body


class HttpRefusal(HTTPException):
    """A refusal: the COMMAND_NACK and its HTTP status, exactly as the gateway answers them.
    The dependency raises it; the handler its ``install`` adds answers it with the NACK as
    the body.  An HTTPException (``detail``: the NACK's JSON text), so without that handler
    Starlette's or FastAPI's still answers with the typed status."""

    def __init__(
        self, status: int, nack: dict[str, Any] | bytes, *, close: bool = False,
        held: HeldAnswer | None = None,
    ) -> None:  # fmt: skip
        body = nack if isinstance(nack, bytes) else encode_json(nack)
        super().__init__(status, body.decode("utf-8", "replace"))
        self.status, self.nack, self.close, self.held = status, nack, close, held
        self.body = body

    @classmethod
    def retry(cls, held: HeldAnswer) -> HttpRefusal:
        """A QoS retransmission: the original answer again, marked, never a second run."""
        return cls(held.status, held.body, held=held)

    async def answer(self, send: Send) -> None:
        await answer(send, self.status, self.nack, self.held, close=self.close)

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


class GuardBase:
    """One POST's request path on a built receiver: framing refusals, the body limit,
    :meth:`Receiver.receive_async`, metrics.  ``owns_receiver``: :meth:`close` closes its
    audit trail too (the receiver was built for this guard alone)."""

    def __init__(
        self, receiver: Receiver, *, metrics: Metrics | None = None, owns_receiver: bool = False
    ) -> None:
        self._owns_receiver = owns_receiver
        self.receiver = receiver
        self.metrics = metrics if metrics is not None else Metrics(receiver)
        self.limit = receiver.max_bytes
        self.nack_type = receiver.config.nack_type
        self.workers = Workers()
        #: Held for a fresh SAFETY message until its answer: ESTOP first (workers.py).
        self.door = Door()
        self.metrics.watch(self.door)
        self._ticker = resolve(None)
        self._closed = False
        #: Refusals' NACK bodies, encoded once (see :meth:`_nack_body`).
        self._nacks: dict[tuple[str, str | None, str | None], bytes] = {}

    @property
    def metrics_endpoint(self) -> Callable[[Request], Awaitable[Response]]:
        """A Starlette endpoint serving these metrics: ``app.add_route("/metrics", ...)``."""
        return self.metrics.endpoint

    @property
    def ready_endpoint(self) -> Callable[[Request], Awaitable[Response]]:
        """A Starlette endpoint answering readiness as the gateway's ``/readyz`` does:
        ``app.add_route("/readyz", ...)`` (503 while the store's fence lies ahead)."""
        return ready_endpoint(self.receiver)

    def close(self) -> None:
        """Stop the worker threads (and close the audit trail of a receiver built for it)."""
        if self._closed:
            return
        self._closed = True
        self.workers.shutdown()
        if self._owns_receiver:
            self.receiver.close()

    def let_go(self) -> None:
        """The current request lets go of the door if it holds it."""
        if self.door.holders:
            self.door.release()

    async def _first(self, fn: Callable[..., Any], *args: Any) -> Any:
        """The urgent lane (only a fresh SAFETY message takes it), holding the door: from
        the start while the early budget lasts, else once authenticated; a refusal lets
        it go, an authenticated one keeps it until this request's answer; a copy of an
        ESTOP in flight or delivered holds none."""
        claimed = getattr(getattr(args[0], "env", None), "msg_id", None) if args else None
        early = self.door.hold_early(claimed)
        result = await self.workers.first(fn, *args)
        if type(result) is NeedsCommit:
            self.door.hold(result.env.msg_id)  # a copy of one in flight or delivered: none
        elif early:
            self.door.release()
        return result

    def ambiguous(self, framing: Framing) -> HttpRefusal | None:
        """Both Content-Length and Transfer-Encoding: refused and closed (RFC 9112)."""
        if framing[1] is None or not framing[2]:
            return None
        reason = "both Content-Length and Transfer-Encoding (RFC 9112 section 6.1)"
        nack = InvalidEnvelopeError(reason).to_nack(None, nack_type=self.nack_type)
        return HttpRefusal(400, nack, close=True)

    async def open(
        self, scope: Scope, receive: Receive, framing: Framing, *, hold: bool = False
    ) -> tuple[Verified, Outcome] | HttpRefusal:
        """One POSTed envelope, checked, authenticated and committed: its :class:`Verified`
        and outcome, or its refusal (a QoS retransmission's: :meth:`HttpRefusal.retry`).
        ``hold``: a fresh SAFETY message keeps the door held after this returns, until the
        caller (which forwards and answers it) calls :meth:`let_go`, also if this raises."""
        refusal = _framing_refusal(framing[0], framing[1], self.limit)
        raw = await _body(receive, self.limit) if refusal is None else refusal
        if not isinstance(raw, bytes):
            # Transport-level refusals: the same NACK as the pipeline's, with the configured
            # type; the code decides the status (errors.HTTP_STATUS); counted like the rest.
            self.metrics.rejected.labels(str(raw.code)).inc()
            return HttpRefusal(raw.http_status, raw.to_nack(None, nack_type=self.nack_type))
        await self.door.enter()
        started = self._ticker.monotonic()
        headers = _Headers(scope["headers"])
        try:
            outcome = await self.receiver.receive_async(raw, headers, self.workers, self._first)
        finally:
            if not hold:
                self.let_go()
        self.metrics.observe(outcome, self._ticker.monotonic() - started)
        if outcome.retry is not None:
            return HttpRefusal.retry(outcome.retry)
        if outcome.error is not None:
            return HttpRefusal(outcome.status, self._nack_body(outcome, outcome.error))
        assert outcome.envelope is not None and outcome.signer is not None
        ack = outcome.ack or {}  # COMMAND_ACK: readable by the rcan SDK
        envelope = as_forwarded(outcome.envelope)
        return Verified(envelope, outcome.signer, outcome.msg_id, outcome.warning, ack), outcome

    def _nack_body(self, outcome: Outcome, error: ReplayAttackError) -> bytes:
        """The NACK's JSON, prebuilt per refusal (code, reason, detail, msg_id): a flood of
        one captured command is answered with the same bytes, encoded once.  A refusal
        whose class adds fields of its own is encoded each time."""
        if type(error).to_nack is not ReplayAttackError.to_nack:
            return encode_json(error.to_nack(outcome.msg_id, nack_type=self.nack_type))
        key = (error.coded_reason, error.detail, outcome.msg_id)
        body = self._nacks.get(key)
        if body is None:
            if len(self._nacks) >= PREBUILT:
                self._nacks.clear()
            body = encode_json(error.to_nack(outcome.msg_id, nack_type=self.nack_type))
            self._nacks[key] = body
        return body


class _Headers(Mapping[str, str]):
    """The request headers as the receiver reads them (lower-case names, the first of a
    repeated one), decoded only if read: a refusal before the token check reads none."""

    __slots__ = ("_decoded", "_raw")

    def __init__(self, raw: list[tuple[bytes, bytes]]) -> None:
        self._raw = raw
        self._decoded: dict[str, str] | None = None

    def _dict(self) -> dict[str, str]:
        if self._decoded is None:
            self._decoded = {k.decode("latin-1"): v.decode("latin-1") for k, v in self._raw[::-1]}
        return self._decoded

    def __getitem__(self, key: str) -> str:
        return self._dict()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._dict())

    def __len__(self) -> int:
        return len(self._dict())


def framing(scope: Scope) -> Framing:
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


def _held_headers(held: HeldAnswer) -> list[tuple[bytes, bytes]]:
    return [(k.encode("latin-1"), v.encode("latin-1")) for k, v in held.headers]


async def answer(
    send: Send, status: int, content: object, held: HeldAnswer | None = None, *, close: bool = False
) -> None:
    """One response, sent as two ASGI messages (what JSONResponse sends, cheaper): JSON
    ``content`` (or its encoding as bytes), or a held answer's body under its own headers."""
    body = content if isinstance(content, bytes) else encode_json(content)
    headers = _held_headers(held) if held else [(b"content-type", b"application/json")]
    headers.append((b"content-length", b"%d" % len(body)))
    if close:
        headers.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


def unclaimed(scope: Scope) -> Scope:
    """``scope`` without a client's ``SIGNER_HEADERS`` (the same scope if it has none)."""
    headers = scope.get("headers")
    if headers is None or not any(name.lower() in SIGNER_HEADER_NAMES for name, _ in headers):
        return scope
    return {**scope, "headers": without_signer(headers)}


def without_signer(headers: Iterable[tuple[bytes, bytes]]) -> list[tuple[bytes, bytes]]:
    return [(name, value) for name, value in headers if name.lower() not in SIGNER_HEADER_NAMES]


def signer_pairs(verified: Verified) -> list[tuple[bytes, bytes]]:
    return [(name.encode(), value.encode()) for name, value in verified.headers()]
