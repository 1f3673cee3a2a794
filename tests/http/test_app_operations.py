"""Operations: readiness, the serve command's startup line, access log and TLS, an upstream
in the working directory, `audit tail --json`, and the Prometheus conventions of /metrics."""

from __future__ import annotations

import asyncio
import datetime
import ipaddress
import json
import sqlite3
import ssl
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
import yaml
from click.testing import CliRunner
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID
from starlette.applications import Starlette

from antireplay.audit import AuditLog, AuditRow, tail
from antireplay.cli import main
from antireplay.cli.demo import JSON, command, load_operator_key, write_demo_config
from antireplay.wiring import create_app, embedded_default
from harness import (
    GatewayProcess,
    accepted_fresh,
    data_losses,
    metrics_router,
    post_after_cut,
    reencoded,
    until,
)
from harness.asgi import demo_app, request
from harness.redis_server import RedisServer
from harness.stores import aged_state


def get(app: Starlette, path: str) -> httpx.Response:
    """One GET to the app in process (ASGI, no socket)."""

    async def once() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://gateway") as http:
            return await http.get(path)

    return asyncio.run(once())


def readyz(gateway: GatewayProcess) -> httpx.Response:
    return httpx.get(f"{gateway.url}/readyz", timeout=10)


def test_readyz_follows_redis_and_the_fence_still_catches_the_loss(tmp_path: Path) -> None:
    redis_server = RedisServer(tmp_path)  # not persistent: a restart loses everything
    redis_server.start()
    gateway = GatewayProcess(write_demo_config(tmp_path, store=redis_server.url))
    gateway.start()
    try:
        assert (readyz(gateway).status_code, readyz(gateway).json()) == (200, {"status": "ready"})
        captured = accepted_fresh(gateway, tmp_path)
        redis_server.stop()
        down = readyz(gateway)
        assert down.status_code == 503, down.text
        assert down.json()["status"] == "unavailable"
        assert "store: STATE_UNAVAILABLE: redis unreachable" in down.json()["reason"]
        assert httpx.get(f"{gateway.url}/healthz", timeout=10).status_code == 200  # liveness
        redis_server.start()  # same port, empty: the captured message is forgotten
        until("readiness after the restart", lambda: readyz(gateway).status_code == 200)
        losses = data_losses(gateway)
        replay = post_after_cut(gateway, reencoded(captured))  # past the memo of bodies
        # Refused by this process's msg_id index (no store read), or by the fence.
        assert replay.status_code in (408, 409), replay.text
        assert data_losses(gateway) == losses  # the probe noticed nothing
        fresh = post_after_cut(gateway, command(load_operator_key(tmp_path)))
        assert (fresh.status_code, fresh.json().get("detail")) == (408, "restart_fence")
        assert data_losses(gateway) == losses + 1  # the commit noticed it, and fenced
    finally:
        gateway.stop()
        redis_server.stop()
    records = tail(tmp_path / "audit.db", 1000)
    assert any(r.code == "STATE_LOST" for r in records), records


def test_readyz_is_503_while_the_audit_trail_cannot_take_an_append(tmp_path: Path) -> None:
    config = embedded_default(tmp_path)
    aged_state(tmp_path / "state.db")  # its first start's fence long past (its own tests)
    app = create_app(config)
    assert get(app, "/readyz").status_code == 200
    holder = sqlite3.connect(config.audit, timeout=0)
    holder.execute("BEGIN IMMEDIATE")  # another writer holds the write lock
    try:
        blocked = get(app, "/readyz")
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    assert blocked.status_code == 503
    assert blocked.json()["reason"] == f"audit {config.audit}: database is locked"
    assert get(app, "/readyz").status_code == 200
    Path(config.audit).rename(tmp_path / "moved.db")  # appends would go nowhere visible
    gone = get(app, "/readyz")
    assert gone.status_code == 503 and "unable to open" in gone.json()["reason"]


def test_below_the_free_space_floors_commands_get_503_and_readyz_says_disk(
    tmp_path: Path,
) -> None:
    """Floors above any real disk's free space: refusals are counted, not written; a command
    gets 503 ``STATE_UNAVAILABLE`` saying disk, as ``/readyz`` does; a fresh ESTOP passes and
    is recorded."""
    floors = {"min_free_bytes": 2**62, "refuse_free_bytes": 2**62}
    with demo_app(tmp_path, audit_space=floors) as app:
        key = load_operator_key(tmp_path)
        ready = get(app, "/readyz")
        assert ready.status_code == 503 and "disk nearly full" in ready.json()["reason"]
        refused = request(app, "POST", "/v1/messages", command(key))
        assert (refused.status_code, refused.json()["code"]) == (503, "STATE_UNAVAILABLE")
        assert "audit_space.refuse_free_bytes" in refused.json()["reason"]
        estop = command(key, type=6, safety_event="ESTOP", cmd="estop")
        assert request(app, "POST", "/v1/messages", estop).status_code == 200
        app.state.receiver.close()
    rows = tail(tmp_path / "audit.db", 100)
    assert [(r.outcome, r.msg_id) for r in rows] == [("accepted", json.loads(estop)["msg_id"])]


def test_metrics_follow_prometheus_conventions(tmp_path: Path) -> None:
    text = get(create_app(embedded_default(tmp_path)), "/metrics").text
    for counter in ("antireplay_watermark_raises", "antireplay_restart_fence_rejections"):
        assert f"# TYPE {counter}_total counter" in text
        assert f"# TYPE {counter} gauge" not in text
    buckets = [line for line in text.splitlines() if "antireplay_latency_seconds_bucket" in line]
    assert buckets[0].startswith('antireplay_latency_seconds_bucket{le="5e-05"}'), buckets


def self_signed(directory: Path) -> tuple[Path, Path]:
    """A certificate for 127.0.0.1 (cert.pem) and its key (key.pem)."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(hours=1))
        .add_extension(
            x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    cert_path, key_path = directory / "cert.pem", directory / "key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return cert_path, key_path


def trusting(cert: Path) -> ssl.SSLContext:
    return ssl.create_default_context(cafile=str(cert))


@contextmanager
def serve(cwd: Path, *args: str) -> Iterator[subprocess.Popen[str]]:
    """The installed ``antireplay`` script (not ``python -m``, which would put the working
    directory on sys.path itself), run in ``cwd``; stopped gracefully afterwards."""
    script = Path(sys.executable).with_name("antireplay")
    proc = subprocess.Popen(
        [str(script), "serve", *args], cwd=cwd, text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        yield proc
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_serve_says_where_it_listens_over_tls_with_access_log_and_a_local_upstream(
    tmp_path: Path,
) -> None:
    config = write_demo_config(tmp_path)
    settings = yaml.safe_load(config.read_text())
    (tmp_path / "robot_here.py").write_text(
        "def handle(envelope):\n    return {'here': envelope['cmd']}\n"
    )
    config.write_text(yaml.safe_dump({**settings, "upstream": "robot_here:handle"}))
    cert, key = self_signed(tmp_path)
    args = ["--config", str(config), "--port", "0", "--access-log"]
    with serve(tmp_path, *args, "--ssl-certfile", str(cert), "--ssl-keyfile", str(key)) as proc:
        assert proc.stdout is not None and proc.stderr is not None
        line = proc.stdout.readline().strip()
        prefix = "listening on https://127.0.0.1:"
        assert line.startswith(prefix), (line, proc.stderr.read() if proc.poll() else "")
        port = int(line[len(prefix) :].split()[0])
        store = f"store sqlite:{tmp_path}/state.db, no state anchor"
        assert line.endswith(f"({store}, audit {tmp_path}/audit.db)")
        with httpx.Client(base_url=f"https://127.0.0.1:{port}", verify=trusting(cert)) as http:
            until("readiness", lambda: http.get("/readyz").status_code == 200)
            raw = command(load_operator_key(tmp_path))
            reply = http.post("/v1/messages", content=raw, headers=JSON)
        assert reply.status_code == 200, reply.text
        assert reply.json()["result"] == {"here": "move_forward"}
        proc.terminate()
        out, _ = proc.communicate(timeout=30)
        assert '"POST /v1/messages HTTP/1.1" 200' in out, out


def test_serve_refuses_half_a_tls_configuration(tmp_path: Path) -> None:
    cert, _ = self_signed(tmp_path)
    result = CliRunner().invoke(main, ["serve", "--ssl-certfile", str(cert)])
    assert result.exit_code == 2
    assert "--ssl-certfile and --ssl-keyfile together" in result.output


def test_audit_tail_json_lines_and_a_full_table_off_a_terminal(tmp_path: Path) -> None:
    path = tmp_path / "audit.db"
    log = AuditLog(path)
    long_id = "m" * 64
    log.append(AuditRow(at=1.5, outcome="accepted", msg_type=1, sender="operator",
                        sender_verified=True, msg_id=long_id))  # fmt: skip
    log.append(AuditRow(at=2.0, outcome="rejected", code="REPLAY_DETECTED", msg_type=1,
                        sender="x\x1b[31m", msg_id=long_id))  # fmt: skip
    log.close()
    with sqlite3.connect(path) as db:  # a row edited behind the trail's back
        db.execute("UPDATE audit SET msg_id = ? WHERE seq = 2", ("\x1b]0;owned\x07[red]x",))
    db.close()
    result = CliRunner().invoke(main, ["audit", "tail", "--json", str(path)])
    assert result.exit_code == 0, result.output
    rows = [json.loads(line) for line in result.output.splitlines()]
    assert [r["seq"] for r in rows] == [1, 2]
    assert rows[0] == {
        "seq": 1, "at": 1.5, "time": "1970-01-01T00:00:01Z", "outcome": "accepted",
        "code": None, "warning": None, "msg_type": 1, "sender": "operator",
        "sender_verified": True, "msg_id": long_id,
    }  # fmt: skip
    assert rows[1]["sender"].startswith("sha256:") and rows[1]["msg_id"].startswith("sha256:")
    assert "\x1b" not in result.output
    table = CliRunner().invoke(main, ["audit", "tail", str(path)])  # not a terminal
    assert table.exit_code == 0
    assert long_id in table.output and "…" not in table.output
    assert "\x1b" not in table.output and rows[1]["msg_id"] in table.output


def test_router_metrics_bind_the_address_given(tmp_path: Path) -> None:
    """``--metrics-host``: the router's metrics answer there, and not on 127.0.0.1."""
    with metrics_router(tmp_path, host="127.0.0.2") as mport:
        reply = httpx.get(f"http://127.0.0.2:{mport}/metrics", timeout=10)
        assert "antireplay_mavlink_forwarded_total" in reply.text
        with pytest.raises(httpx.ConnectError):
            httpx.get(f"http://127.0.0.1:{mport}/metrics", timeout=10)
