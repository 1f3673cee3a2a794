"""End to end: `antireplay serve` as a real subprocess, spoken to over loopback with httpx."""

from __future__ import annotations

import json
import re
import shutil
import signal
import socket
import sqlite3
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, HTTPServer
from pathlib import Path
from typing import Any

import httpx
import msgspec
import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import mldsa
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rcan import RCANMessage
from rcan.signing import MLDSAKeyPair, sign_message

from antireplay import ManualClock, SecurityConfig
from antireplay.audit import AuditLog, verify
from antireplay.audit import tail as audit_tail
from antireplay.cli.demo import JSON, command, load_operator_key, write_demo_config
from antireplay.core.errors import StateUnavailableError
from antireplay.rcan.auth import b64encode
from antireplay.rcan.envelope import SDK_SIGNED_FIELDS, Envelope, canonical_bytes
from antireplay.state.redis import RedisStore
from antireplay.wiring import create_app, embedded_default
from harness import (
    GatewayProcess,
    free_port,
    metric,
    post,
    recording_upstream,
    run_threads,
    serving,
    state_rows,
)
from harness.asgi import demo_app, request, send_command
from harness.redis_server import RedisServer
from harness.stores import aged_state
from tests.fuzz.targets import http_app


@pytest.fixture(scope="module")
def state(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("gateway")


@pytest.fixture(scope="module")
def gateway(state: Path) -> Iterator[GatewayProcess]:
    with serving(write_demo_config(state)) as gw:
        yield gw


@pytest.fixture
def http(gateway: GatewayProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=gateway.url, timeout=10) as client:
        yield client


def test_accept_forwards_to_upstream(http: httpx.Client, state: Path) -> None:
    raw = command(load_operator_key(state))
    reply = post(http, raw)
    assert reply.status_code == 200
    body = reply.json()
    assert body["accepted"] and body["result"]["executed"] == "move_forward"


def test_replay_is_409_nack(http: httpx.Client, state: Path) -> None:
    raw = command(load_operator_key(state))
    post(http, raw)
    reply = post(http, raw)
    assert reply.status_code == 409
    assert reply.json()["code"] == "REPLAY_DETECTED" and reply.json()["type"] == 18


def test_stale_capture_is_408(http: httpx.Client, state: Path) -> None:
    reply = post(http, command(load_operator_key(state), 40))
    assert (reply.status_code, reply.json()["code"]) == (408, "MESSAGE_STALE")


def test_forged_then_genuine(http: httpx.Client, state: Path) -> None:
    genuine = json.loads(command(load_operator_key(state)))
    forged = {**genuine, "params": {"distance_m": 50}}
    assert post(http, json.dumps(forged).encode()).status_code == 401
    assert post(http, json.dumps(genuine).encode()).status_code == 200


def test_flood_records_nothing_and_opens_no_replay(http: httpx.Client, state: Path) -> None:
    key = load_operator_key(state)
    victim = command(key)
    post(http, victim)
    before = state_rows(state)
    for i in range(200):
        body = {**json.loads(command(key)), "msg_id": f"garbage-{i}", "cmd": "x"}
        assert post(http, json.dumps(body).encode()).status_code == 401
    assert state_rows(state) == before
    assert post(http, victim).status_code == 409


def test_estop_duplicate_processed_and_audited(http: httpx.Client, state: Path) -> None:
    estop = command(load_operator_key(state), type=6, safety_event="ESTOP", cmd="estop")
    assert post(http, estop).json().get("warning") is None
    again = post(http, estop)
    assert again.status_code == 200 and again.json()["warning"] == "REPLAY_DETECTED"
    msg_id = json.loads(estop)["msg_id"]
    records = [r for r in AuditLog(state / "audit.db").tail(1000) if r.msg_id == msg_id]
    assert [r.warning for r in records] == [None, "REPLAY_DETECTED"]


def test_stale_estop_rejected(http: httpx.Client, state: Path) -> None:
    stale = command(load_operator_key(state), 11, type=6, safety_event="ESTOP", cmd="estop")
    assert post(http, stale).status_code == 408


def test_metrics_count_what_happened(http: httpx.Client, state: Path) -> None:
    key = load_operator_key(state)
    accepted = metric(http, "antireplay_accepted_total")
    replays = metric(http, "antireplay_rejected_total", '{code="REPLAY_DETECTED"}')
    raw = command(key)
    post(http, raw)
    for _ in range(3):
        post(http, raw)
    assert metric(http, "antireplay_accepted_total") == accepted + 1
    assert metric(http, "antireplay_rejected_total", '{code="REPLAY_DETECTED"}') == replays + 3


def test_restart_then_replay_rejected(gateway: GatewayProcess, state: Path) -> None:
    raw = command(load_operator_key(state))
    assert httpx.post(f"{gateway.url}/v1/messages", content=raw, headers=JSON).status_code == 200
    gateway.stop()
    gateway.start()
    reply = httpx.post(f"{gateway.url}/v1/messages", content=raw, headers=JSON)
    assert reply.status_code == 409
    assert verify(state / "audit.db").ok


def test_transport_refusals(http: httpx.Client) -> None:
    plain = http.post("/v1/messages", content=b"{}", headers={"content-type": "text/plain"})
    assert (plain.status_code, plain.json()["code"]) == (415, "UNSUPPORTED_MEDIA_TYPE")
    huge = b'{"x":"' + b"a" * 70_000 + b'"}'
    reply = post(http, huge)
    assert reply.status_code == 413 and reply.json()["code"] == "PAYLOAD_TOO_LARGE"
    counted = http.get("/metrics").text
    for code in ("PAYLOAD_TOO_LARGE", "UNSUPPORTED_MEDIA_TYPE"):
        assert f'antireplay_rejected_total{{code="{code}"}} 1.0' in counted
    assert http.get("/healthz").json()["status"] == "ok"


def _stamp(body: bytes) -> bytes:
    return body.replace(b"NOW", str(int(time.time())).encode())


HOSTILE_BODIES = {
    "msg_id not UTF-8": b'{"msg_id":"a\xff","cmd":"x","target":"t","rcan":"3.2","timestamp":NOW}',
    "cmd not UTF-8": b'{"msg_id":"a","cmd":"x\xc3","target":"t","rcan":"3.2","timestamp":NOW}',
    "params not UTF-8": (
        b'{"msg_id":"a","cmd":"x","target":"t","rcan":"3.2","timestamp":NOW,"params":{"k":"\xfe"}}'
    ),
    "sig.kid not UTF-8": (
        b'{"msg_id":"a","cmd":"x","target":"t","rcan":"3.2","timestamp":NOW,'
        b'"sig":{"alg":"ed25519","kid":"\xff","value":"AA"}}'
    ),
    "huge timestamp": b'{"msg_id":"a","cmd":"x","target":"t","rcan":"3.2","timestamp":'
    + b"9" * 400
    + b"}",
    "huge timestamp_ms": b'{"msg_id":"a","cmd":"x","target":"t","rcan":"3.2","timestamp_ms":'
    + b"9" * 400
    + b"}",
    "huge type": b'{"msg_id":"a","cmd":"x","target":"t","rcan":"3.2","timestamp":NOW,"type":'
    + b"9" * 30
    + b"}",
}


@pytest.mark.parametrize("name", sorted(HOSTILE_BODIES))
def test_hostile_bytes_get_a_typed_4xx_never_500(http: httpx.Client, name: str) -> None:
    reply = post(http, _stamp(HOSTILE_BODIES[name]))
    assert reply.status_code == 400, reply.text
    assert reply.json()["code"] in {"INVALID_ENVELOPE", "INVALID_TIMESTAMP"}


def test_max_body_bytes_above_64k_is_the_limit_in_force(tmp_path: Path) -> None:
    gw = GatewayProcess(write_demo_config(tmp_path, max_body_bytes=200_000))
    gw.start()
    try:
        key = load_operator_key(tmp_path)
        big = command(key, params={"blob": "a" * 100_000})
        assert 100_000 < len(big) < 200_000
        reply = httpx.post(f"{gw.url}/v1/messages", content=big, headers=JSON)
        assert reply.status_code == 200, reply.text
        over = command(key, params={"blob": "a" * 200_001})
        reply = httpx.post(f"{gw.url}/v1/messages", content=over, headers=JSON)
        assert (reply.status_code, reply.json()["code"]) == (413, "PAYLOAD_TOO_LARGE")
    finally:
        gw.stop()


def _raw_exchange(url: str, request: bytes) -> tuple[bytes, bool]:
    """Send raw bytes to the real server; return the reply and whether the server closed."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        sock.sendall(request)
        reply = b""
        while True:
            try:
                chunk = sock.recv(65536)
            except TimeoutError:
                return reply, False  # still open after 10 s: not closed
            if not chunk:
                return reply, True
            reply += chunk


def test_content_length_with_transfer_encoding_is_refused_and_closed(
    gateway: GatewayProcess, state: Path
) -> None:
    body = command(load_operator_key(state))
    chunked = f"{len(body):x}\r\n".encode() + body + b"\r\n0\r\n\r\n"
    request = (
        b"POST /v1/messages HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        b"Content-Type: application/json\r\n"
        + f"Content-Length: {len(chunked)}\r\n".encode()
        + b"Transfer-Encoding: chunked\r\n\r\n"
        + chunked
    )
    reply, closed = _raw_exchange(gateway.url, request)
    head = reply.split(b"\r\n\r\n", 1)[0].lower()
    assert head.startswith(b"http/1.1 400"), reply[:200]
    assert b"\r\nconnection: close" in head
    assert closed
    # The message itself was never processed: sent properly, it is still accepted.
    assert httpx.post(f"{gateway.url}/v1/messages", content=body, headers=JSON).status_code == 200


@pytest.mark.parametrize(
    ("declared", "code"),
    [("9" * 5000, "PAYLOAD_TOO_LARGE"), ("2920\u00b97", "INVALID_ENVELOPE"),
     ("0" * 30 + "2", "INVALID_ENVELOPE")],
    ids=["5000 digits", "superscript digit", "leading zeros"],
)  # fmt: skip
def test_content_length_values_get_typed_answers(
    gateway: GatewayProcess, declared: str, code: str
) -> None:
    """Found by fuzzing the app (int() of 5000 digits and of '¹' raised): never a 500."""
    status, reply = http_app().request(
        [(b"content-type", b"application/json"), (b"content-length", declared.encode())], b"{}"
    )
    assert 400 <= status < 500 and json.loads(reply)["code"] == code
    request = (
        b"POST /v1/messages HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        + b"Content-Length: " + declared.encode() + b"\r\nConnection: close\r\n\r\n{}"
    )  # fmt: skip
    raw_reply, _ = _raw_exchange(gateway.url, request)
    assert re.match(rb"HTTP/1.1 4\d\d ", raw_reply), raw_reply[:200]


@settings(max_examples=2_000, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    body=st.one_of(
        st.binary(max_size=200),
        st.dictionaries(st.text(max_size=10), st.text(max_size=10), max_size=6).map(
            lambda d: json.dumps(d).encode()
        ),
    ),
    ctype=st.sampled_from(
        ["application/json", "application/json; charset=utf-8", "text/plain", ""]
    ),
)
def test_hypothesis_bad_requests_get_4xx_with_code(
    http: httpx.Client, body: bytes, ctype: str
) -> None:
    reply = http.post("/v1/messages", content=body, headers={"content-type": ctype})
    assert 400 <= reply.status_code < 500
    assert reply.json()["code"]


# --- upstream over HTTP ----------------------------------------------------------------------


class _Robot(BaseHTTPRequestHandler):
    def do_POST(self) -> None:
        length = int(self.headers["content-length"])
        envelope = json.loads(self.rfile.read(length))
        body = json.dumps({"moved": envelope["params"]["distance_m"]}).encode()
        self.send_response(201)
        self.send_header("content-type", "application/json")
        self.send_header("content-length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: Any) -> None:
        """Quiet."""


def test_http_upstream_and_upstream_failure(tmp_path: Path) -> None:
    robot = HTTPServer(("127.0.0.1", 0), _Robot)
    threading.Thread(target=robot.serve_forever, daemon=True).start()
    up = tmp_path / "up"
    up.mkdir()
    good = GatewayProcess(write_demo_config(up, upstream=f"http://127.0.0.1:{robot.server_port}/"))
    down = tmp_path / "down"
    down.mkdir()
    bad = GatewayProcess(write_demo_config(down, upstream=f"http://127.0.0.1:{free_port()}/"))
    good.start()
    bad.start()
    try:
        reply = httpx.post(
            f"{good.url}/v1/messages", content=command(load_operator_key(up)), headers=JSON
        )
        assert (reply.status_code, reply.json()["result"]) == (201, {"moved": 0.5})
        reply = httpx.post(
            f"{bad.url}/v1/messages", content=command(load_operator_key(down)), headers=JSON
        )
        assert reply.status_code == 502
    finally:
        good.stop()
        bad.stop()
        robot.shutdown()


def test_sdk_compat_mitm_field_never_reaches_upstream(tmp_path: Path) -> None:
    pair = MLDSAKeyPair.generate()
    public = mldsa.MLDSA65PublicKey.from_public_bytes(pair.public_key)
    (tmp_path / "sdk.pub.pem").write_bytes(
        public.public_bytes(
            serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
        )
    )
    sdk_key = {"kid": pair.key_id, "owner": "operator", "alg": "ml-dsa-65",
               "public_keys": [str(tmp_path / "sdk.pub.pem")], "scopes": ["control"]}  # fmt: skip
    with recording_upstream() as (url, received):
        config = write_demo_config(tmp_path, sdk_compat=True, keys=[sdk_key], upstream=url)
        gw = GatewayProcess(config)
        gw.start()
        try:
            msg = RCANMessage(cmd="move_forward", params={"distance_m": 1.0},
                              target="rcan://registry.rcan.dev/acme/arm/v2/unit-001")  # fmt: skip
            genuine = sign_message(msg, pair).to_dict()
            for field, value in (("loa", 3), ("presence_verified", True), ("read_only", True)):
                forged = json.dumps({**genuine, field: value}).encode()
                reply = httpx.post(f"{gw.url}/v1/messages", content=forged, headers=JSON)
                assert (reply.status_code, reply.json()["code"]) == (403, "SCOPE_DENIED")
            assert received == []
            reply = httpx.post(f"{gw.url}/v1/messages", content=json.dumps(genuine), headers=JSON)
            assert reply.status_code == 200, reply.text
            (seen,) = received
            assert set(json.loads(seen.body)) == {*SDK_SIGNED_FIELDS, "rcan_version", "sig"}
        finally:
            gw.stop()


# --- two replicas on one Redis -------------------------------------------------------------------


def test_two_replicas_on_one_redis(tmp_path: Path, redis_url: str) -> None:
    shared = redis_url.rsplit("/", 1)[0] + "/5"
    a_dir, b_dir = tmp_path / "a", tmp_path / "b"
    a_dir.mkdir()
    b_dir.mkdir()
    a_cfg = write_demo_config(a_dir, store=shared)
    b_cfg = write_demo_config(b_dir, store=shared)
    # Both replicas trust the same operator key.
    (b_dir / "operator.pub.pem").write_bytes((a_dir / "operator.pub.pem").read_bytes())
    # An existing deployment: the first contact with a new (or wiped) Redis raises the
    # shared fence to now; messages stamped after fence + skew pass.
    fence = RedisStore(shared).verify().fence
    while time.time() <= fence + 5.0:  # a condition on the real clock, not a guess
        time.sleep(0.05)
    a, b = GatewayProcess(a_cfg), GatewayProcess(b_cfg)
    a.start()
    b.start()
    try:
        key = load_operator_key(a_dir)
        raw = command(key)
        first = httpx.post(f"{a.url}/v1/messages", content=raw, headers=JSON)
        assert first.status_code == 200, first.text
        replay = httpx.post(f"{b.url}/v1/messages", content=raw, headers=JSON)
        assert (replay.status_code, replay.json()["code"]) == (409, "REPLAY_DETECTED")
    finally:
        a.stop()
        b.stop()


def _refuses_connections(url: str) -> bool:
    host, port = url.removeprefix("http://").split(":")
    try:
        socket.create_connection((host, int(port)), timeout=1).close()
    except OSError:
        return True
    return False


def test_sigterm_with_requests_in_flight_answers_them_and_loses_no_record(
    tmp_path: Path,
) -> None:
    """SIGTERM arrives while N requests are inside the gateway (held by the upstream)."""
    in_flight = 8
    arrived, release = threading.Semaphore(0), threading.Event()

    def hold() -> None:
        arrived.release()
        release.wait(timeout=60)

    with recording_upstream(before_answer=hold) as (url, _):
        gw = GatewayProcess(write_demo_config(tmp_path, upstream=url))
        gw.start()
        key = load_operator_key(tmp_path)
        replies: list[int] = []

        def client() -> None:
            raw = command(key)
            reply = httpx.post(f"{gw.url}/v1/messages", content=raw, headers=JSON)
            replies.append(reply.status_code)

        threads = [threading.Thread(target=client) for _ in range(in_flight)]
        try:
            for thread in threads:
                thread.start()
            for _ in range(in_flight):  # every request is now inside the gateway, awaiting upstream
                if not arrived.acquire(timeout=30):
                    pytest.fail("requests did not reach the upstream")
            assert gw.proc is not None
            gw.proc.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + 30
            while not _refuses_connections(gw.url):  # shutdown has begun: the listener is closed
                if time.monotonic() > deadline or gw.proc.poll() is not None:
                    pytest.fail("gateway did not start a graceful shutdown")
            assert replies == []  # still in flight when the signal was handled
            release.set()
            for thread in threads:
                thread.join(timeout=30)
            # uvicorn re-raises the signal once it has shut down gracefully
            assert gw.proc.wait(timeout=30) in (0, -signal.SIGTERM)
        finally:
            release.set()
            gw.stop()
    assert replies == [200] * in_flight
    records = AuditLog(tmp_path / "audit.db").tail(1000)
    assert sum(r.outcome == "accepted" for r in records) == in_flight
    assert verify(tmp_path / "audit.db").ok


def test_lost_sqlite_state_is_fenced_logged_and_audited_on_the_real_cli(tmp_path: Path) -> None:
    """kill -9, then the state database vanishes (its witness stays): the restarted gateway
    says so on stderr, audits STATE_LOST, and refuses the captured command."""
    gw = GatewayProcess(write_demo_config(tmp_path))
    gw.start()
    key = load_operator_key(tmp_path)
    raw = command(key)
    assert httpx.post(f"{gw.url}/v1/messages", content=raw, headers=JSON).status_code == 200
    assert gw.proc is not None
    gw.proc.kill()
    gw.proc.wait()
    gw.proc = None
    for victim in tmp_path.glob("state.db*"):  # `rm state.db*`
        victim.unlink()
    gw.start()
    try:
        replay = httpx.post(f"{gw.url}/v1/messages", content=raw, headers=JSON)
        assert replay.status_code == 408 and replay.json()["detail"] == "restart_fence"
        assert (
            'antireplay_state_data_loss_total{backend="sqlite"} 1.0'
            in httpx.get(f"{gw.url}/metrics").text
        )
    finally:
        gw.stop()
    assert gw.stderr_text is not None and "replay state" in gw.stderr_text
    codes = [r.code for r in AuditLog(tmp_path / "audit.db").tail(50)]
    assert "STATE_LOST" in codes


def test_concurrent_exact_replays_are_each_audited_before_their_answer(
    gateway: GatewayProcess, state: Path
) -> None:
    """The byte-identical shortcut runs on the event loop and awaits its group-committed audit
    row: every 409 a client holds already has its durable row, or was folded into its
    sender's summary by the rate limit (counted before the answer)."""
    raw = command(load_operator_key(state))
    folded = '{class="unauthenticated"}'
    with httpx.Client(base_url=gateway.url, timeout=10) as http:
        assert post(http, raw).status_code == 200
        before = sum(r.code == "REPLAY_DETECTED" for r in audit_tail(state / "audit.db", 500))
        folded_before = metric(http, "antireplay_audit_refusals_folded_total", folded)
        answers: list[int] = []

        def replay(_: int) -> None:
            with httpx.Client(base_url=gateway.url, timeout=10) as own:
                answers.append(post(own, raw).status_code)

        run_threads(16, replay)
        rows = audit_tail(state / "audit.db", 500)
        folded_now = metric(http, "antireplay_audit_refusals_folded_total", folded) - folded_before
    assert answers == [409] * 16
    assert sum(r.code == "REPLAY_DETECTED" for r in rows) - before + folded_now == 16
    assert verify(state / "audit.db").chain_ok


def test_estop_reaches_the_robot_with_its_audit_trail_and_state_deleted(tmp_path: Path) -> None:
    """``rm audit.db`` under the running gateway, then ``rm state.db*`` too: a fresh ESTOP is
    still forwarded (with a warning, counted, said once on stderr), a copy of it still as
    the flagged duplicate; every other command gets 503 and never reaches the robot."""
    with recording_upstream() as (url, received):
        gw = GatewayProcess(write_demo_config(tmp_path, upstream=url))
        gw.start()
        key = load_operator_key(tmp_path)
        try:
            with httpx.Client(base_url=gw.url, timeout=10) as http:
                assert post(http, command(key)).status_code == 200
                (tmp_path / "audit.db").unlink()
                estop = command(key, type=6, safety_event="ESTOP", cmd="estop")
                answers = [post(http, estop), post(http, estop), post(http, command(key))]
                for victim in tmp_path.glob("state.db*"):
                    victim.unlink()
                later = command(key, type=6, safety_event="ESTOP", cmd="halt")
                answers += [post(http, later), post(http, command(key))]
                assert metric(http, "antireplay_estops_unaudited_total") == 3
                assert metric(http, "antireplay_audit_held_rows") == 3
                labels = '{warning="AUDIT_UNAVAILABLE"}'
                assert metric(http, "antireplay_warnings_total", labels) == 1
        finally:
            gw.stop()
    said = [(a.status_code, a.json().get("warning") or a.json().get("code")) for a in answers]
    assert said == [
        (200, "AUDIT_UNAVAILABLE"), (200, "REPLAY_DETECTED"), (503, "STATE_UNAVAILABLE"),
        (200, "STATE_UNAVAILABLE"), (503, "STATE_UNAVAILABLE"),
    ]  # fmt: skip
    assert [json.loads(r.body)["cmd"] for r in received] == ["move_forward", *["estop"] * 2, "halt"]
    assert gw.stderr_text is not None and gw.stderr_text.count("audit trail unavailable (") == 1


def test_a_command_carrying_a_safety_event_is_refused_and_never_forwarded(
    tmp_path: Path,
) -> None:
    """A COMMAND (type 1) with ``safety_event: ESTOP``, signed by a trusted key (built past
    the parser, which refuses to sign it), is malformed, not a command an upstream could
    read as an ESTOP."""
    with recording_upstream() as (url, received):
        gw = GatewayProcess(write_demo_config(tmp_path, upstream=url))
        gw.start()
        try:
            key = load_operator_key(tmp_path)
            body = {**json.loads(command(key)), "cmd": "halt", "safety_event": "ESTOP"}
            del body["sig"]
            value = b64encode(key.sign(canonical_bytes(msgspec.convert(body, Envelope))))
            sig = {"alg": "ed25519", "kid": "operator", "value": value}
            raw = json.dumps({**body, "sig": sig}).encode()
            reply = httpx.post(f"{gw.url}/v1/messages", content=raw, headers=JSON)
        finally:
            gw.stop()
    assert (reply.status_code, reply.json()["code"]) == (400, "INVALID_ENVELOPE")
    assert "only a SAFETY" in reply.json()["reason"]
    assert received == []


# --- readiness and metrics of a gateway in process ----------------------------------------------


def test_readyz_is_503_when_redis_may_evict_and_so_is_a_command(tmp_path: Path) -> None:
    skew_s = SecurityConfig().skew_s  # a new deployment's fence refuses messages stamped up to this
    server = RedisServer(tmp_path)
    server.start()
    try:
        clock = ManualClock(wall=time.time())
        with demo_app(tmp_path, clock, store=server.url) as app:  # a new deployment: fenced
            clock.advance(skew_s + 1)  # messages stamped this far ahead pass that fence
            assert request(app, "GET", "/readyz").status_code == 200
            server.client().config_set("maxmemory-policy", "allkeys-lru")
            probe = request(app, "GET", "/readyz")
            assert probe.status_code == 503, probe.text
            assert "maxmemory-policy allkeys-lru" in probe.json()["reason"]
            refused = send_command(app, tmp_path, -(skew_s + 1))
            assert (refused.status_code, refused.json()["code"]) == (503, "STATE_UNAVAILABLE")
            server.client().config_set("maxmemory-policy", "noeviction")
            assert request(app, "GET", "/readyz").status_code == 200
            assert send_command(app, tmp_path, -(skew_s + 1)).status_code == 200
    finally:
        server.stop()


def test_readyz_is_503_while_another_process_holds_the_state_write_lock(tmp_path: Path) -> None:
    with demo_app(tmp_path, store=f"sqlite:{tmp_path / 'state.db'}") as app:
        assert request(app, "GET", "/readyz").status_code == 200
        holder = sqlite3.connect(tmp_path / "state.db", timeout=0)
        holder.execute("BEGIN IMMEDIATE")
        try:
            blocked = request(app, "GET", "/readyz")
        finally:
            holder.execute("ROLLBACK")
            holder.close()
        assert blocked.status_code == 503
        assert blocked.json()["reason"].endswith("state.db: database is locked")
        assert request(app, "GET", "/readyz").status_code == 200
        assert send_command(app, tmp_path).status_code == 200


def test_a_deleted_state_file_stays_missing_and_unready_and_commands_are_refused(
    tmp_path: Path,
) -> None:
    db = tmp_path / "state.db"
    with demo_app(tmp_path) as app:
        assert send_command(app, tmp_path).status_code == 200  # readers and the writer are open
        assert request(app, "GET", "/readyz").status_code == 200
        shutil.copy(db, tmp_path / "copy.db")
        db.unlink()
        for restored in (False, False, True):  # then a copy put in its place: still refused
            if restored:
                shutil.copy(tmp_path / "copy.db", db)
            probe = request(app, "GET", "/readyz")
            assert probe.status_code == 503, probe.text
            assert "deleted or replaced while running" in probe.json()["reason"]
            refused = send_command(app, tmp_path)
            assert (refused.status_code, refused.json()["code"]) == (503, "STATE_UNAVAILABLE")
            metrics = request(app, "GET", "/metrics")
            assert metrics.status_code == 200
            assert db.exists() is restored  # no probe, lookup or scrape made a new database


def test_metrics_counters_keep_their_last_value_while_the_store_is_down(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    app = create_app(embedded_default(tmp_path))
    loss = 'antireplay_state_data_loss_total{backend="sqlite"}'
    assert f"{loss} 0.0" in request(app, "GET", "/metrics").text

    def down() -> dict[str, float]:
        raise StateUnavailableError("sqlite: down")

    monkeypatch.setattr(app.state.receiver.cache.store, "status", down)
    text = request(app, "GET", "/metrics").text
    assert (
        f"{loss} 0.0" in text and 'antireplay_watermark_raises_total{backend="sqlite"} 0.0' in text
    )
    assert 'antireplay_cache_entries{backend="sqlite"} NaN' in text  # a gauge may be unknown
    counters = [line for line in text.splitlines() if "_total{" in line]
    assert counters and not any(line.endswith("NaN") for line in counters), counters


def test_the_served_gateway_commits_an_accepted_command_as_one_operation(tmp_path: Path) -> None:
    """``antireplay serve`` on its SQLite state: each accepted command is ONE operation of
    the state's group commit (its entry and its audit row together), not two; its row is in
    the trail."""
    config = write_demo_config(tmp_path)
    aged_state(tmp_path / "state.db")  # history: no first start's fence
    key = load_operator_key(tmp_path)
    ops = "antireplay_group_commit_operations_total"
    with serving(config) as gateway:
        before = metric(gateway, ops, '{log="state"}')
        sent = [command(key) for _ in range(5)]
        assert all(post(gateway, raw).status_code == 200 for raw in sent)
        # 5 (two each before: 10), and at most one outbox delete per fsynced drain (~1 s)
        assert 5 <= metric(gateway, ops, '{log="state"}') - before <= 7
    ids = {json.loads(raw)["msg_id"] for raw in sent}
    rows = [r for r in audit_tail(tmp_path / "audit.db", 20) if r.msg_id in ids]
    assert sorted(r.outcome for r in rows) == ["accepted"] * 5
