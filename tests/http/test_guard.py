"""The in-process guard: the gateway, a FastAPI app behind :class:`Guard` and a FastAPI route
using :class:`RcanGuard` give the same answer to every demo step (one request path), and
the verified signer reaches the application and the upstream, never a client's claim."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import threading
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn
from cryptography.hazmat.primitives.asymmetric import ed25519
from fastapi import Depends, FastAPI, Header, Request, WebSocket
from starlette.testclient import TestClient, WebSocketDenialResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from antireplay.audit import tail
from antireplay.cli.demo import JSON, command, load_operator_key, write_demo_config
from antireplay.config import AppConfig
from antireplay.core.clock import ManualClock
from antireplay.core.errors import UpstreamFailedError
from antireplay.http.guard import SIGNER_HEADERS, GuardBase, Verified
from antireplay.http.workers import Door
from antireplay.rcan.auth import Signer
from antireplay.rcan.envelope import encode, parse
from antireplay.rcan.receive import Outcome, Receiver
from antireplay.rcan.steps import Done
from antireplay.wiring import Guard, RcanGuard, build_receiver, create_app
from harness import free_port, recording_upstream, state_rows, until
from harness.asgi import LIMIT, NOW, Answer, call, config
from harness.envelopes import signed

#: What the module:function upstream of the gateway under test was called with.
CALLS: list[tuple[dict[str, Any], Signer]] = []


def record(envelope: dict[str, Any], signer: Signer) -> dict[str, Any]:
    """The gateway's ``module:function`` upstream: takes the signer as its second parameter."""
    CALLS.append((envelope, signer))
    return {"executed": envelope["cmd"]}


@dataclass
class Target:
    """One way in: the app to call, what the application was handed, its receiver's state."""

    name: str
    app: ASGIApp
    #: (what the application was handed, the body it read, its request headers)
    handed: list[tuple[Verified, bytes, dict[str, str]]] = field(default_factory=list)


def guarded_app(cfg: AppConfig, clock: ManualClock) -> tuple[Target, Guard]:
    """A FastAPI robot API behind the Guard middleware."""
    api = FastAPI()
    target = Target("middleware", api)

    @api.post("/v1/messages")
    async def move(request: Request) -> dict[str, Any]:
        verified: Verified = request.state.antireplay
        target.handed.append((verified, await request.body(), dict(request.headers)))
        return verified.ack

    guard = Guard(api, cfg, clock=clock)
    api.add_route("/metrics", guard.metrics_endpoint)
    target.app = guard
    return target, guard


def dependency_app(cfg: AppConfig, clock: ManualClock) -> tuple[Target, RcanGuard]:
    """A FastAPI route taking the verified message as a dependency."""
    api = FastAPI()
    guard = RcanGuard(cfg, clock=clock)
    guard.install(api)
    target = Target("dependency", api)

    @api.post("/v1/messages")
    async def move(
        request: Request,
        verified: Verified = Depends(guard),  # noqa: B008 - a local guard: Annotated cannot see it
    ) -> dict[str, Any]:
        # The dependency read the body: the route takes the envelope from ``verified``.
        target.handed.append((verified, b"", dict(request.headers)))
        return verified.ack

    return target, guard


def ways_in(tmp_path: Path, clock: ManualClock) -> tuple[list[Target], list[Guard | RcanGuard]]:
    """The gateway, the middleware and the dependency, each on its own SQLite state."""
    public = tmp_path / "operator.pub.pem"
    upstream = "tests.http.test_guard:record"
    gateway = Target(
        "gateway", create_app(config(tmp_path / "gw", public, upstream=upstream), clock=clock)
    )
    middleware, guard = guarded_app(config(tmp_path / "mw", public), clock)
    dependency, dep = dependency_app(config(tmp_path / "dep", public), clock)
    return [gateway, middleware, dependency], [guard, dep]


@pytest.fixture
def targets(
    tmp_path: Path,
) -> Iterator[tuple[ed25519.Ed25519PrivateKey, ManualClock, list[Target]]]:
    write_demo_config(tmp_path)  # the operator's key pair
    clock = ManualClock(wall=NOW)
    ways, guards = ways_in(tmp_path, clock)
    CALLS.clear()
    yield load_operator_key(tmp_path), clock, ways
    for guard in guards:
        guard.close()


def test_every_demo_step_gets_the_gateways_answer_from_middleware_and_dependency(
    targets: tuple[ed25519.Ed25519PrivateKey, ManualClock, list[Target]], tmp_path: Path
) -> None:
    key, clock, ways = targets

    def signed(age_s: float = 0.0, **fields: Any) -> bytes:
        return command(key, timestamp=clock.wall() - age_s, **fields)

    first = signed()
    genuine = json.loads(signed())
    forged = json.dumps({**genuine, "cmd": "arm_motors"}).encode()
    estop = signed(type=6, safety_event="ESTOP", cmd="estop")
    flood = [json.dumps({**json.loads(signed()), "cmd": "x"}).encode() for _ in range(20)]
    json_ct = [(b"content-type", b"application/json")]
    chunked = [*json_ct, (b"transfer-encoding", b"chunked")]
    steps: list[tuple[str, str, bytes, dict[str, Any]]] = [
        ("operator: move_forward", "accepted", first, {}),
        ("attacker: exact replay", "REPLAY_DETECTED", first, {}),
        ("attacker: capture from 40 s ago", "MESSAGE_STALE", signed(40), {}),
        ("attacker: forged msg with victim's msg_id", "SIGNATURE_INVALID", forged, {}),
        ("operator: the genuine message", "accepted", json.dumps(genuine).encode(), {}),
        *[("attacker: forged flood", "SIGNATURE_INVALID", f, {}) for f in flood],
        ("attacker: replay after the flood", "REPLAY_DETECTED", first, {}),
        ("operator: ESTOP", "accepted", estop, {}),
        ("network: duplicate fresh ESTOP", "accepted", estop, {}),
        ("attacker: ESTOP from 11 s ago", "MESSAGE_STALE",
         signed(11, type=6, safety_event="ESTOP", cmd="estop"), {}),
        ("text/plain", "UNSUPPORTED_MEDIA_TYPE", signed(),
         {"headers": [(b"content-type", b"text/plain")]}),
        ("declared too large", "PAYLOAD_TOO_LARGE", b"x" * (LIMIT + 1), {}),
        ("streamed too large", "PAYLOAD_TOO_LARGE", b"x" * (LIMIT + 1),
         {"headers": chunked, "length": False}),
        ("both Content-Length and Transfer-Encoding", "INVALID_ENVELOPE", signed(),
         {"headers": chunked}),
        ("content-length not a number", "INVALID_ENVELOPE", signed(),
         {"headers": [*json_ct, (b"content-length", b"12a")], "length": False}),
        ("not JSON", "INVALID_ENVELOPE", b"{not json", {}),
        ("no signature", "SIGNATURE_REQUIRED",
         json.dumps({k: v for k, v in json.loads(signed()).items() if k != "sig"}).encode(), {}),
    ]  # fmt: skip

    async def play() -> list[list[Answer]]:
        return [[await call(w.app, raw, **opts) for w in ways] for _, _, raw, opts in steps]

    answers = asyncio.run(play())
    for (name, expected, _, _), (gateway, *others) in zip(steps, answers, strict=True):
        for other in others:
            assert other.status == gateway.status, name
            if expected == "accepted":
                assert gateway.status == 200, name
                assert other.json() == {k: v for k, v in gateway.json().items() if k != "result"}
            else:
                assert other.body == gateway.body, name  # byte for byte: the NACK itself
                assert gateway.json()["code"] == expected, (name, gateway.body)
    dup_estop = answers[[s[0] for s in steps].index("network: duplicate fresh ESTOP")]
    assert {a.json()["warning"] for a in dup_estop} == {"REPLAY_DETECTED"}
    both = answers[[s[0] for s in steps].index("both Content-Length and Transfer-Encoding")]
    assert {a.headers.get(b"connection") for a in both} == {b"close"}

    accepted_ids = [json.loads(raw)["msg_id"] for _, e, raw, _ in steps if e == "accepted"]
    assert [env["msg_id"] for env, _ in CALLS] == accepted_ids  # the gateway's upstream
    for way in ways[1:]:
        assert [v.msg_id for v, _, _ in way.handed] == accepted_ids, way.name  # exactly once
        for verified, _, _ in way.handed:
            assert verified.signer.owner == verified.signer.kid == "operator"
            assert verified.signer.scopes == frozenset({"control", "safety"})
        assert [v.warning for v, _, _ in way.handed] == [None, None, None, "REPLAY_DETECTED"]
    for (envelope, signer), (verified, body, headers) in zip(CALLS, ways[1].handed, strict=True):
        assert envelope == verified.envelope  # the gateway forwards what the guard hands over
        assert signer == verified.signer
        # Behind the middleware the body is the canonical re-encoding, its length fixed.
        assert body == encode(parse(body)) and json.loads(body) == verified.envelope
        assert headers["content-length"] == str(len(body))
    # The flood recorded nothing anywhere: three accepted msg_ids in each real SQLite store.
    assert {state_rows(tmp_path / d) for d in ("gw", "mw", "dep")} == {3}


def test_after_a_restart_every_way_in_still_refuses_the_replay(
    targets: tuple[ed25519.Ed25519PrivateKey, ManualClock, list[Target]], tmp_path: Path
) -> None:
    key, clock, ways = targets
    first = command(key, timestamp=clock.wall())

    async def send(to: list[Target]) -> list[Answer]:
        return [await call(way.app, first) for way in to]

    assert [a.status for a in asyncio.run(send(ways))] == [200, 200, 200]
    restarted, guards = ways_in(tmp_path, clock)  # new receivers on the same files
    try:
        replays = asyncio.run(send(restarted))
    finally:
        for guard in guards:
            guard.close()
    assert {(a.status, a.json()["code"]) for a in replays} == {(409, "REPLAY_DETECTED")}
    assert len({a.body for a in replays}) == 1


def test_the_application_sees_the_verified_signer_never_the_clients_claim(
    targets: tuple[ed25519.Ed25519PrivateKey, ManualClock, list[Target]],
) -> None:
    key, clock, (_, middleware, dependency) = targets
    lies = [
        (b"content-type", b"application/json"),
        (b"rcan-signer-owner", b"admin"),
        (b"rcan-signer-scopes", b"*"),
        (b"rcan-msg-id", b"other"),
    ]
    raw = command(key, timestamp=clock.wall())

    async def both() -> None:
        await call(middleware.app, raw, lies)
        await call(dependency.app, raw, lies)

    asyncio.run(both())
    for verified, _, seen in (middleware.handed[0], dependency.handed[0]):
        assert [seen[name] for name in SIGNER_HEADERS] == [
            "operator", "operator", "control,safety", verified.msg_id
        ]  # fmt: skip
        assert verified.signer.owner == "operator"


def test_http_upstream_gets_the_signer_headers_and_no_client_copies(tmp_path: Path) -> None:
    with recording_upstream() as (url, received):
        write_demo_config(tmp_path)
        clock = ManualClock(wall=NOW)
        app = create_app(
            config(tmp_path / "gw", tmp_path / "operator.pub.pem", upstream=url), clock=clock
        )
        raw = command(load_operator_key(tmp_path), timestamp=clock.wall())
        forged_claims = [
            (b"content-type", b"application/json"),
            (b"rcan-signer-owner", b"admin"),
            (b"rcan-signer-kid", b"root"),
            (b"rcan-signer-scopes", b"*"),
            (b"rcan-msg-id", b"x"),
            (b"x-client", b"1"),
        ]
        reply = asyncio.run(call(app, raw, forged_claims))
        assert reply.status == 200, reply.body
    seen = received[0].headers
    assert len(received) == 1
    assert seen["rcan-signer-owner"] == "operator"
    assert seen["rcan-signer-kid"] == "operator"
    assert seen["rcan-signer-scopes"] == "control,safety"
    assert seen["rcan-msg-id"] == json.loads(raw)["msg_id"]
    assert "x-client" not in seen  # the gateway builds the upstream request itself


def test_a_one_parameter_upstream_gets_the_envelope_alone(tmp_path: Path) -> None:
    write_demo_config(tmp_path)
    clock = ManualClock(wall=NOW)
    cfg = config(
        tmp_path / "gw", tmp_path / "operator.pub.pem", upstream="antireplay.cli.demo:robot"
    )
    raw = command(load_operator_key(tmp_path), timestamp=clock.wall())
    reply = asyncio.run(call(create_app(cfg, clock=clock), raw))
    assert (reply.status, reply.json()["result"]["executed"]) == (200, "move_forward")


def test_receive_async_returns_the_settled_outcome_after_its_audit_row_is_durable(
    tmp_path: Path,
) -> None:
    write_demo_config(tmp_path)
    clock = ManualClock(wall=NOW)
    cfg = config(tmp_path / "state", tmp_path / "operator.pub.pem")
    receiver = build_receiver(cfg, clock)
    raw = command(load_operator_key(tmp_path), timestamp=clock.wall())
    msg_id = json.loads(raw)["msg_id"]

    async def twice() -> tuple[Outcome, int, Outcome, int]:
        assert receiver.audit is not None
        accepted = await receiver.receive_async(raw, {})
        receiver.audit.drain()  # committed (in the state's outbox), not queued: moved now
        rows_then = len(tail(cfg.audit, 100))  # another connection
        refused = await receiver.receive_async(raw, {})
        receiver.audit.drain()
        return accepted, rows_then, refused, len(tail(cfg.audit, 100))

    try:
        accepted, rows_after_accept, refused, rows_after_refusal = asyncio.run(twice())
    finally:
        assert receiver.audit is not None
        receiver.audit.close()
    assert isinstance(accepted, Outcome) and accepted.accepted and accepted.msg_id == msg_id
    assert accepted.signer is not None and accepted.signer.owner == "operator"
    assert (refused.accepted, refused.status, refused.code) == (False, 409, "REPLAY_DETECTED")
    assert (rows_after_accept, rows_after_refusal) == (1, 2)
    first, second = tail(cfg.audit, 2)  # oldest first
    assert (first.outcome, first.msg_id) == ("accepted", msg_id)
    assert (second.outcome, second.code) == ("rejected", "REPLAY_DETECTED")


def test_guard_under_uvicorn_serves_metrics_and_stops_its_workers(tmp_path: Path) -> None:
    write_demo_config(tmp_path)
    clock = ManualClock(wall=NOW)
    target, guard = guarded_app(config(tmp_path / "mw", tmp_path / "operator.pub.pem"), clock)
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(target.app, port=port, log_level="warning"))
    thread = threading.Thread(target=server.run)
    thread.start()
    until("uvicorn to listen", lambda: server.started)
    raw = command(load_operator_key(tmp_path), timestamp=clock.wall())
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10) as http:
            answers = [http.post("/v1/messages", content=raw, headers=JSON) for _ in range(2)]
            text = http.get("/metrics").text
    finally:
        server.should_exit = True
        thread.join(timeout=30)
    assert [a.status_code for a in answers] == [200, 409]
    assert answers[1].json()["code"] == "REPLAY_DETECTED"
    assert "antireplay_accepted_total 1.0" in text
    assert 'antireplay_rejected_total{code="REPLAY_DETECTED"} 1.0' in text
    assert guard.receiver.stats.accepted == 1
    assert not any(t.is_alive() for t in guard.workers._threads)  # lifespan shutdown stopped them


def test_add_middleware_form_guards_the_path_and_leaves_other_routes_alone(
    tmp_path: Path,
) -> None:
    write_demo_config(tmp_path)
    clock = ManualClock(wall=NOW)
    api = FastAPI()
    api.add_middleware(
        Guard, config=config(tmp_path / "mw", tmp_path / "operator.pub.pem"), clock=clock
    )
    handed: list[Verified] = []

    @api.post("/v1/messages")
    async def move(request: Request) -> dict[str, Any]:
        handed.append(request.state.antireplay)
        return {"ok": True}

    @api.post("/notes")
    async def notes(request: Request) -> dict[str, Any]:
        return {"bytes": len(await request.body())}  # not a guarded path: untouched

    raw = command(load_operator_key(tmp_path), timestamp=clock.wall())

    async def play() -> list[Answer]:
        return [await call(api, raw), await call(api, raw), await call(api, b"hi", path="/notes")]

    accepted, replay, other = asyncio.run(play())
    assert (accepted.status, accepted.json()) == (200, {"ok": True})
    assert (replay.status, replay.json()["code"]) == (409, "REPLAY_DETECTED")
    assert (other.status, other.json()) == (200, {"bytes": 2})
    assert [v.msg_id for v in handed] == [json.loads(raw)["msg_id"]]


def test_fastapi_stays_optional() -> None:
    code = (
        "import sys, antireplay, antireplay.http.app, antireplay.http.dependency; "
        "print(antireplay.RcanGuard.__name__, 'fastapi' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["RcanGuard", "False"]


def test_a_qos_retransmission_gets_the_apps_original_answer_and_never_reaches_it_again(
    tmp_path: Path,
) -> None:
    write_demo_config(tmp_path)
    clock = ManualClock(wall=NOW)
    target, guard = guarded_app(config(tmp_path / "mw", tmp_path / "operator.pub.pem"), clock)
    dependency, dep = dependency_app(config(tmp_path / "dep", tmp_path / "operator.pub.pem"), clock)
    raw = command(load_operator_key(tmp_path), timestamp=clock.wall(), qos=1)

    async def twice(app: ASGIApp) -> list[Answer]:
        return [await call(app, raw), await call(app, raw)]

    try:
        first, again = asyncio.run(twice(target.app))
        behind_dependency = asyncio.run(twice(dependency.app))
    finally:
        guard.close()
        dep.close()
    assert (first.status, again.status) == (200, 200)
    assert again.json() == {**first.json(), "duplicate": True}
    assert again.headers[b"rcan-duplicate"] == b"true"
    assert len(target.handed) == 1  # executed once
    assert [a.status for a in behind_dependency] == [200, 409]
    assert len(dependency.handed) == 1


LIES = {"rcan-signer-owner": "admin", "rcan-signer-scopes": "*", "rcan-msg-id": "other"}


def _signer_claims(headers: dict[str, str]) -> dict[str, str]:
    return {name: value for name, value in headers.items() if name in SIGNER_HEADERS}


def test_a_websocket_is_refused_on_a_guarded_path_and_stripped_of_signer_claims_elsewhere(
    tmp_path: Path,
) -> None:
    write_demo_config(tmp_path)
    clock = ManualClock(wall=NOW)
    started: list[bool] = []

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        started.append(True)
        yield

    api = FastAPI(lifespan=lifespan)
    executed: list[str] = []

    @api.websocket("/v1/messages")
    async def commands(socket: WebSocket) -> None:
        await socket.accept()
        executed.append(await socket.receive_text())

    @api.websocket("/ws")
    async def echo(socket: WebSocket) -> None:
        await socket.accept()
        await socket.send_json(dict(socket.headers))
        await socket.close()

    @api.get("/whoami")
    async def whoami(request: Request) -> dict[str, str]:
        return dict(request.headers)

    guard = Guard(api, config(tmp_path / "mw", tmp_path / "operator.pub.pem"), clock=clock)
    unsigned = json.dumps({"cmd": "move_forward", "msg_id": "m-1"})
    with TestClient(guard) as client:  # lifespan reaches the app untouched
        with (
            pytest.raises(WebSocketDenialResponse) as denied,
            client.websocket_connect("/v1/messages", headers=JSON) as socket,
        ):
            socket.send_text(unsigned)
        with client.websocket_connect("/ws", headers=LIES) as socket:
            echoed = socket.receive_json()
        plain = client.get("/whoami", headers=LIES).json()
    assert (denied.value.status_code, denied.value.json()["code"]) == (405, "INVALID_ENVELOPE")
    assert executed == []
    assert _signer_claims(echoed) == {} and _signer_claims(plain) == {}
    assert started == [True]
    assert not any(t.is_alive() for t in guard.workers._threads)  # lifespan shutdown ran


def test_a_websocket_on_a_guarded_path_is_closed_1008_by_a_server_without_denial_responses(
    tmp_path: Path,
) -> None:
    write_demo_config(tmp_path)
    reached: list[str] = []

    async def app(scope: Scope, receive: Receive, send: Send) -> None:
        reached.append(scope["type"])

    guard = Guard(app, config(tmp_path / "mw", tmp_path / "operator.pub.pem"))
    scope = {
        "type": "websocket", "asgi": {"version": "3.0"}, "scheme": "ws", "path": "/v1/messages",
        "raw_path": b"/v1/messages", "query_string": b"", "root_path": "", "headers": [],
        "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 80), "subprotocols": [],
    }  # fmt: skip
    incoming: list[Message] = [{"type": "websocket.connect"}]
    sent: list[Message] = []

    async def receive() -> Message:
        return incoming.pop(0) if incoming else {"type": "websocket.disconnect", "code": 1000}

    async def send(message: Message) -> None:
        sent.append(message)

    try:
        asyncio.run(guard(scope, receive, send))
    finally:
        guard.close()
    assert [(m["type"], m["code"]) for m in sent] == [("websocket.close", 1008)]
    assert reached == []


def test_behind_the_dependency_routes_see_the_verified_signer_never_the_clients_claim(
    tmp_path: Path,
) -> None:
    write_demo_config(tmp_path)
    clock = ManualClock(wall=NOW)
    api = FastAPI()
    guard = RcanGuard(config(tmp_path / "dep", tmp_path / "operator.pub.pem"), clock=clock)
    guard.install(api)
    seen: list[dict[str, str]] = []

    @api.post("/v1/messages")
    async def move(
        request: Request,
        verified: Verified = Depends(guard),  # noqa: B008 - a local guard: Annotated cannot see it
        owner: str | None = Header(None, alias="rcan-signer-owner"),
    ) -> dict[str, Any]:
        seen.append({**dict(request.headers), "param": owner or ""})
        return verified.ack

    @api.get("/whoami")
    async def whoami(request: Request) -> dict[str, str]:
        return dict(request.headers)

    @api.websocket("/ws")
    async def echo(socket: WebSocket) -> None:
        await socket.accept()
        await socket.send_json(dict(socket.headers))
        await socket.close()

    raw = command(load_operator_key(tmp_path), timestamp=clock.wall())
    try:
        with TestClient(api) as client:
            accepted = client.post("/v1/messages", content=raw, headers={**JSON, **LIES})
            plain = client.get("/whoami", headers=LIES).json()
            with client.websocket_connect("/ws", headers=LIES) as socket:
                echoed = socket.receive_json()
    finally:
        guard.close()
    assert accepted.status_code == 200, accepted.text
    assert _signer_claims(seen[0]) == {
        "rcan-signer-owner": "operator", "rcan-signer-kid": "operator",
        "rcan-signer-scopes": "control,safety", "rcan-msg-id": json.loads(raw)["msg_id"],
    }  # fmt: skip
    assert seen[0]["param"] == "operator"
    assert _signer_claims(plain) == {} and _signer_claims(echoed) == {}


@pytest.fixture
def door_guard(tmp_path: Path) -> Iterator[tuple[ed25519.Ed25519PrivateKey, ManualClock, Guard]]:
    """The middleware on its own SQLite state, and the operator's key."""
    write_demo_config(tmp_path)
    clock = ManualClock(wall=NOW)
    _, guard = guarded_app(config(tmp_path / "mw", tmp_path / "operator.pub.pem"), clock)
    yield load_operator_key(tmp_path), clock, guard
    guard.close()


def test_other_requests_wait_at_the_door_while_a_fresh_estop_is_answered(
    door_guard: tuple[ed25519.Ed25519PrivateKey, ManualClock, Guard],
) -> None:
    """An ordinary command arriving while an ESTOP is between its signature check and its
    answer starts only after the ESTOP's answer; the door is open again afterwards."""
    key, clock, guard = door_guard
    estop = command(key, timestamp=clock.wall(), type=6, safety_event="ESTOP", cmd="estop")
    ordinary = command(key, timestamp=clock.wall())
    urgent = guard.workers.first

    async def scenario() -> list[tuple[str, int]]:
        checked, answered = asyncio.Event(), asyncio.Event()
        done: list[tuple[str, int]] = []

        async def slow_first(fn: Any, *args: Any) -> Any:
            result = await urgent(fn, *args)
            checked.set()
            await answered.wait()  # the ESTOP still in flight
            return result

        guard.workers.first = slow_first  # type: ignore[method-assign,assignment]

        async def send(name: str, body: bytes) -> None:
            done.append((name, (await call(guard, body)).status))

        first = asyncio.create_task(send("estop", estop))
        await checked.wait()
        second = asyncio.create_task(send("ordinary", ordinary))
        for _ in range(20):
            await asyncio.sleep(0)
        assert (guard.door.waited, done) == (1, [])  # at the door, not in the receiver
        answered.set()
        await asyncio.wait_for(asyncio.gather(first, second), 10)
        return done

    assert asyncio.run(scenario()) == [("estop", 200), ("ordinary", 200)]
    assert (guard.door.holders, guard.door.timeouts) == (set(), 0)


def test_a_forged_safety_message_lets_the_door_go_and_an_authentic_one_holds_it(
    door_guard: tuple[ed25519.Ed25519PrivateKey, ManualClock, Guard],
) -> None:
    """With no budget for holds before the signature check (a forged flood spent it), an
    authentic ESTOP still holds the door from its authentication; a forged one never does."""
    key, clock, guard = door_guard
    guard.door = Door(early_per_s=0.001, early_burst=0.0, clock=clock)
    genuine = json.loads(command(key, timestamp=clock.wall(), type=6, safety_event="ESTOP"))
    forged = json.dumps({**genuine, "cmd": "arm_motors"}).encode()
    steps = guard.receiver.steps

    async def held_after(raw: bytes) -> bool:
        parsed = steps.parse(raw)
        assert not isinstance(parsed, Done)
        await guard._first(steps.authenticate, parsed, None, {})
        held = asyncio.current_task() in guard.door.holders
        guard.door.release()
        return held

    async def scenario() -> tuple[bool, bool, bool]:
        forged_held = await held_after(forged)
        genuine_held = await held_after(json.dumps(genuine).encode())
        guard.door = Door(clock=clock)  # the default budget: the forged one held it early
        return forged_held, genuine_held, await held_after(forged)

    assert asyncio.run(scenario()) == (False, True, False)
    assert guard.door.holders == set()


def test_an_estop_holds_the_door_until_the_robot_has_answered_it(tmp_path: Path) -> None:
    """The door opens after the ESTOP is forwarded and answered, not when it is verified:
    a slow robot behind the middleware still has the ESTOP to itself."""
    write_demo_config(tmp_path)
    clock = ManualClock(wall=NOW)
    key = load_operator_key(tmp_path)
    reached, answered = asyncio.Event(), asyncio.Event()

    async def robot(scope: Scope, receive: Receive, send: Send) -> None:
        if scope["state"]["antireplay"].envelope["cmd"] == "estop":
            reached.set()
            await answered.wait()
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"{}"})

    guard = Guard(robot, config(tmp_path / "mw", tmp_path / "operator.pub.pem"), clock=clock)
    estop = command(key, timestamp=clock.wall(), type=6, safety_event="ESTOP", cmd="estop")

    async def scenario() -> list[tuple[str, int]]:
        done: list[tuple[str, int]] = []

        async def send(name: str, body: bytes) -> None:
            done.append((name, (await call(guard, body)).status))

        first = asyncio.create_task(send("estop", estop))
        await reached.wait()  # verified, committed, at the robot
        second = asyncio.create_task(send("ordinary", command(key, timestamp=clock.wall())))
        for _ in range(20):
            await asyncio.sleep(0)
        assert (guard.door.waited, done) == (1, [])
        answered.set()
        await asyncio.wait_for(asyncio.gather(first, second), 10)
        return done

    try:
        assert asyncio.run(scenario()) == [("estop", 200), ("ordinary", 200)]
    finally:
        guard.close()
    assert guard.door.holders == set()


def test_a_refusal_flood_is_answered_with_its_nack_encoded_once(receiver: Receiver) -> None:
    """The same refusal (code, reason, msg_id) is answered with the same bytes, encoded
    once, equal to its NACK; another refusal gets its own; a refusal class with fields of
    its own (an upstream failure's ``delivered``) is encoded each time."""
    guard = GuardBase(receiver)
    try:
        raw = signed(msg_id="flooded")
        assert receiver.receive(raw).accepted
        first, again = receiver.receive(raw), receiver.receive(raw)
        assert first.error is not None and again.error is not None
        body = guard._nack_body(first, first.error)
        assert guard._nack_body(again, again.error) is body
        assert json.loads(body) == first.nack
        stale = receiver.receive(signed(msg_id="old", timestamp=NOW - 3600))
        assert stale.error is not None
        assert json.loads(guard._nack_body(stale, stale.error))["ref_msg_id"] == "old"
        failed = Outcome(False, 502, msg_id="up", error=UpstreamFailedError("down", delivered="no"))
        assert failed.error is not None
        assert guard._nack_body(failed, failed.error) is not guard._nack_body(failed, failed.error)
    finally:
        guard.close()


def test_a_cached_nack_is_never_another_messages(receiver: Receiver) -> None:
    """Two replays refused with the same code, reason and detail but different msg_ids: each
    body names its own msg_id (the cache key holds it); ``None`` and ``""`` differ too."""
    guard = GuardBase(receiver)
    try:
        bodies = []
        for msg_id in ("replay-a", "replay-b"):
            raw = signed(msg_id=msg_id)
            assert receiver.receive(raw).accepted
            again = receiver.receive(raw)
            assert again.error is not None
            bodies.append((again, json.loads(guard._nack_body(again, again.error))))
        (a, body_a), (b, body_b) = bodies
        assert a.error is not None and b.error is not None
        assert (a.error.coded_reason, a.error.detail) == (b.error.coded_reason, b.error.detail)
        assert body_a["ref_msg_id"] == "replay-a" and body_b["ref_msg_id"] == "replay-b"
        assert body_a == a.nack and body_b == b.nack
        blank = Outcome(False, 409, msg_id="", error=a.error)
        unnamed = Outcome(False, 409, msg_id=None, error=a.error)
        assert guard._nack_body(blank, a.error) != guard._nack_body(unnamed, a.error)
    finally:
        guard.close()
