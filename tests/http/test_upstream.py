"""The gateway's upstream and the Guard's response path: an upstream's error status is a
COMMAND_NACK the SDK reads as an error (audited), a bodyless answer is an ACK, an
unencodable or slow module:function upstream is a 502, a streamed answer passes through
as it comes and is held byte for byte (plus the marker) for a QoS retransmission, and
the signer headers are the Guard's alone on every route."""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import AsyncIterator, Iterator
from http.server import BaseHTTPRequestHandler, HTTPServer
from pathlib import Path
from typing import Any, ClassVar

import pytest
from click.testing import CliRunner
from cryptography.hazmat.primitives.asymmetric import ed25519
from fastapi import Depends, FastAPI, Request
from rcan import RCANResponse
from starlette._utils import get_route_path
from starlette.responses import Response, StreamingResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from antireplay.audit import verify
from antireplay.cli import main
from antireplay.cli.demo import command, load_operator_key, write_demo_config
from antireplay.core.clock import ManualClock
from antireplay.http.guard import Verified
from antireplay.http.middleware import route_path
from antireplay.http.upstream import takes_signer
from antireplay.rcan.auth import Signer
from antireplay.wiring import Guard, RcanGuard, create_app
from harness.asgi import NOW, Answer, call, config

#: Released by the test: the blocking module:function upstream waits for it.
RELEASE = threading.Event()


def unencodable(envelope: dict[str, Any]) -> object:
    return object()


def blocking(envelope: dict[str, Any]) -> dict[str, Any]:
    RELEASE.wait(30)
    return {"late": True}


def jammed(envelope: dict[str, Any]) -> None:
    raise RuntimeError("arm jammed")


class _Robot(BaseHTTPRequestHandler):
    """An HTTP upstream answering ``status`` with ``body`` (none when empty)."""

    status: ClassVar[int] = 200
    body: ClassVar[bytes] = b""

    def do_POST(self) -> None:
        self.rfile.read(int(self.headers["content-length"]))
        self.send_response(self.status)
        if self.body:
            self.send_header("content-type", "application/json")
            self.send_header("content-length", str(len(self.body)))
        self.end_headers()
        self.wfile.write(self.body)

    def log_message(self, *args: Any) -> None:
        """Quiet."""


@pytest.fixture
def key(tmp_path: Path) -> ed25519.Ed25519PrivateKey:
    write_demo_config(tmp_path)
    return load_operator_key(tmp_path)


@pytest.fixture
def robot() -> Iterator[tuple[str, type[_Robot]]]:
    server = HTTPServer(("127.0.0.1", 0), _Robot)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_port}/", _Robot
    server.shutdown()


def gateway(tmp_path: Path, upstream: str, **overrides: Any) -> ASGIApp:
    cfg = config(tmp_path / "gw", tmp_path / "operator.pub.pem", upstream=upstream, **overrides)
    return create_app(cfg, clock=ManualClock(wall=NOW))


def twice(app: ASGIApp, raw: bytes) -> list[Answer]:
    async def play() -> list[Answer]:
        return [await call(app, raw), await call(app, raw)]

    return asyncio.run(play())


def test_an_upstream_error_status_is_a_nack_with_its_status_and_body_and_its_retry_the_same(
    tmp_path: Path, key: ed25519.Ed25519PrivateKey, robot: tuple[str, type[_Robot]]
) -> None:
    url, handler = robot
    handler.status, handler.body = 503, b'{"err":"busy"}'
    app = gateway(tmp_path, url)
    raw = command(key, timestamp=NOW, qos=1)
    first, again = twice(app, raw)
    assert (first.status, again.status) == (503, 503)
    nack = first.json()
    assert (nack["code"], nack["delivered"], nack["upstream_status"], nack["result"]) == (
        "UPSTREAM_FAILED", "yes", 503, {"err": "busy"},
    )  # fmt: skip
    response = RCANResponse.from_dict(nack)
    assert (response.ok, response.status) == (False, "error")
    assert again.json() == {**nack, "duplicate": True}
    handler.status, handler.body = 500, b""  # no body: still a failure, never the ACK
    bare = asyncio.run(call(app, command(key, timestamp=NOW)))
    assert (bare.status, bare.json()["delivered"], bare.json()["result"]) == (500, "yes", None)
    metrics = app.state.metrics  # type: ignore[attr-defined]
    assert metrics.upstream_errors._value.get() == 2


@pytest.mark.parametrize("status", [204, 304])
def test_an_upstream_answer_without_a_body_is_the_ack_with_status_200(
    tmp_path: Path, key: ed25519.Ed25519PrivateKey, robot: tuple[str, type[_Robot]], status: int
) -> None:
    url, handler = robot
    handler.status, handler.body = status, b""
    reply = asyncio.run(call(gateway(tmp_path, url), command(key, timestamp=NOW)))
    assert reply.status == 200
    assert (reply.json()["status"], reply.json()["upstream_status"]) == ("ok", status)
    assert RCANResponse.from_dict(reply.json()).ok


def test_an_unencodable_module_result_is_a_502_delivered_unknown(
    tmp_path: Path, key: ed25519.Ed25519PrivateKey
) -> None:
    app = gateway(tmp_path, "tests.http.test_upstream:unencodable")
    reply = asyncio.run(call(app, command(key, timestamp=NOW)))
    assert reply.status == 502
    assert (reply.json()["code"], reply.json()["delivered"]) == ("UPSTREAM_FAILED", "unknown")


def test_a_module_upstream_past_its_timeout_is_a_502_and_a_retry_outwaits_it(
    tmp_path: Path, key: ed25519.Ed25519PrivateKey
) -> None:
    RELEASE.clear()
    app = gateway(tmp_path, "tests.http.test_upstream:blocking", upstream_timeout_s=0.2)
    assert app.state.receiver.answer_wait_s > 0.2  # type: ignore[attr-defined]
    try:
        reply = asyncio.run(call(app, command(key, timestamp=NOW)))
    finally:
        RELEASE.set()  # the thread the timed-out call left behind
    assert reply.status == 502
    assert (reply.json()["code"], reply.json()["delivered"]) == ("UPSTREAM_FAILED", "unknown")


def test_an_upstream_failure_is_audited_under_the_verified_owner(
    tmp_path: Path, key: ed25519.Ed25519PrivateKey
) -> None:
    app = gateway(tmp_path, "tests.http.test_upstream:jammed")
    raw = command(key, timestamp=NOW)
    reply = asyncio.run(call(app, raw))
    assert reply.status == 502
    app.state.receiver.audit.close()  # type: ignore[attr-defined]
    audit = tmp_path / "gw" / "audit.db"
    out = CliRunner().invoke(main, ["audit", "tail", "--json", str(audit)])
    rows = [json.loads(line) for line in out.output.splitlines()]
    assert [(r["outcome"], r["code"], r["warning"], r["sender"], r["msg_id"]) for r in rows] == [
        ("accepted", None, None, "operator", json.loads(raw)["msg_id"]),
        ("rejected", "UPSTREAM_FAILED", "delivered=unknown", "operator", json.loads(raw)["msg_id"]),
    ]
    report = verify(audit)
    assert (report.broken_at, report.head) == (None, "match")


# --- the Guard around an application ---------------------------------------------------------


def test_signer_headers_never_reach_the_app_and_a_guarded_path_takes_only_post(
    tmp_path: Path, key: ed25519.Ed25519PrivateKey
) -> None:
    seen: list[dict[bytes, bytes]] = []

    async def app(scope: Scope, receive: Receive, send: Send) -> None:
        seen.append(dict(scope["headers"]))
        await Response("ok")(scope, receive, send)

    guard = Guard(app, config(tmp_path / "mw", tmp_path / "operator.pub.pem"))
    claims = [(b"rcan-signer-owner", b"admin"), (b"RCAN-Signer-Scopes", b"*")]

    async def play() -> list[Answer]:
        return [
            await call(guard, b"", claims, method="GET", path="/notes"),
            await call(guard, b"{}", claims, method="PUT", path="/notes"),
            await call(guard, b"", claims, method="GET", path="/v1/messages"),
        ]

    try:
        other, put, get = asyncio.run(play())
    finally:
        guard.close()
    assert (other.status, put.status) == (200, 200)
    assert all(b"rcan-signer-owner" not in h and b"RCAN-Signer-Scopes" not in h for h in seen)
    assert len(seen) == 2  # the GET on the guarded path never reached the app
    assert (get.status, get.json()["code"]) == (405, "INVALID_ENVELOPE")


def held_app(tmp_path: Path, app: ASGIApp) -> Guard:
    return Guard(
        app, config(tmp_path / "mw", tmp_path / "operator.pub.pem"), clock=ManualClock(wall=NOW)
    )


def test_a_streamed_answer_passes_through_as_it_comes_and_its_retry_gets_it_whole(
    tmp_path: Path, key: ed25519.Ed25519PrivateKey
) -> None:
    release = asyncio.Event()

    async def chunks() -> AsyncIterator[bytes]:
        yield b'{"step":1,'
        await release.wait()
        yield b'"step2":2}'

    async def app(scope: Scope, receive: Receive, send: Send) -> None:
        await StreamingResponse(chunks(), media_type="application/json")(scope, receive, send)

    guard = held_app(tmp_path, app)
    raw = command(key, timestamp=NOW, qos=1)
    first_chunk_before_the_end: list[bool] = []

    async def original() -> list[Message]:
        sent: list[Message] = []
        scope = _scope()

        bodies = [raw]

        async def receive() -> Message:
            if bodies:
                return {"type": "http.request", "body": bodies.pop(), "more_body": False}
            await asyncio.Event().wait()  # the client stays connected
            raise AssertionError

        async def send(message: Message) -> None:
            sent.append(message)
            if message["type"] == "http.response.body" and not release.is_set():
                first_chunk_before_the_end.append(message.get("more_body", False))
                release.set()

        await guard(scope, receive, send)
        return sent

    async def play() -> tuple[list[Message], Answer]:
        # Bounded only so a Guard that buffers (first byte at the end) fails, not hangs.
        return await asyncio.wait_for(original(), 10), await call(guard, raw)

    try:
        sent, again = asyncio.run(play())
    finally:
        guard.close()
    assert first_chunk_before_the_end == [True]
    body = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    assert json.loads(body) == {"step": 1, "step2": 2}
    assert again.status == 200 and again.json() == {"step": 1, "step2": 2, "duplicate": True}


def test_an_app_that_raises_drops_the_in_flight_answer_at_once(
    tmp_path: Path, key: ed25519.Ed25519PrivateKey
) -> None:
    async def app(scope: Scope, receive: Receive, send: Send) -> None:
        await send({"type": "http.response.start", "status": 200, "headers": []})
        raise RuntimeError("arm jammed")

    guard = held_app(tmp_path, app)
    guard.receiver.answer_wait_s = 3600  # a waiting retry would hang the test
    raw = command(key, timestamp=NOW, qos=1)
    msg_id = json.loads(raw)["msg_id"]

    async def play() -> Answer:
        with pytest.raises(RuntimeError):
            await call(guard, raw)
        assert not guard.receiver.answers.in_flight(msg_id)
        return await call(guard, raw)

    try:
        again = asyncio.run(play())
    finally:
        guard.close()
    assert (again.status, again.json()["code"]) == (409, "REPLAY_DETECTED")


def test_a_held_answer_keeps_status_headers_and_bytes_apart_from_the_marker(
    tmp_path: Path, key: ed25519.Ed25519PrivateKey
) -> None:
    answers = {
        "text": (b"moved", "text/plain"),
        "json": ('{"say": "\u00e9",  "n": 1.50}'.encode(), "application/json"),
    }
    kind: list[str] = []

    async def app(scope: Scope, receive: Receive, send: Send) -> None:
        body, media = answers[kind[0]]
        headers = {"x-robot": "arm-1", "location": "/jobs/7"}
        await Response(body, 202, headers=headers, media_type=media)(scope, receive, send)

    guard = held_app(tmp_path, app)
    try:
        for name, (body, _) in answers.items():
            kind[:] = [name]
            first, again = twice(guard, command(key, timestamp=NOW, qos=1))
            assert (first.status, again.status) == (202, 202)
            for header in (b"x-robot", b"location", b"content-type"):
                assert again.headers[header] == first.headers[header]
            assert again.headers[b"rcan-duplicate"] == b"true"
            assert again.headers[b"content-length"] == b"%d" % len(again.body)
            expected = body if name == "text" else body[:-1] + b',"duplicate":true}'
            assert (first.body, again.body) == (body, expected)
    finally:
        guard.close()


def _scope() -> Scope:
    return {
        "type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST",
        "scheme": "http", "path": "/v1/messages", "raw_path": b"/v1/messages",
        "query_string": b"", "root_path": "", "client": ("127.0.0.1", 1),
        "server": ("127.0.0.1", 80), "headers": [(b"content-type", b"application/json")],
    }  # fmt: skip


# --- small rules -------------------------------------------------------------------------


def with_retries(envelope: dict[str, Any], retries: int = 3) -> None: ...


def with_signer(envelope: dict[str, Any], signer: object) -> None: ...


def annotated(envelope: dict[str, Any], who: Signer) -> None: ...


def test_only_a_second_parameter_named_signer_or_typed_signer_gets_the_signer() -> None:
    assert not takes_signer(with_retries)
    assert takes_signer(with_signer)
    assert takes_signer(annotated)  # a string annotation here (future annotations)
    assert not takes_signer(lambda envelope, *rest: None)


@pytest.mark.parametrize(
    ("path", "root"),
    [("/api/v1/messages", "/api"), ("/apiv1/messages", "/api"), ("/api", "/api"), ("/x", "")],
)
def test_the_guarded_path_is_the_one_starlette_routes(path: str, root: str) -> None:
    scope = {"type": "http", "path": path, "root_path": root}
    assert route_path(scope) == get_route_path(scope)


def test_rcan_guard_without_install_still_answers_with_the_typed_status(
    tmp_path: Path, key: ed25519.Ed25519PrivateKey
) -> None:
    api = FastAPI()
    guard = RcanGuard(
        config(tmp_path / "dep", tmp_path / "operator.pub.pem"), clock=ManualClock(wall=NOW)
    )

    @api.post("/v1/messages")
    async def move(
        request: Request,
        verified: Verified = Depends(guard),  # noqa: B008 - a local guard
    ) -> dict[str, Any]:
        return verified.ack

    try:
        first, again = twice(api, command(key, timestamp=NOW))
    finally:
        guard.close()
    assert (first.status, again.status) == (200, 409)
    assert json.loads(again.json()["detail"])["code"] == "REPLAY_DETECTED"
