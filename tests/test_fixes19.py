"""Findings of the issue-19 review: readiness that says what a commit would meet, state files
never re-created by a reader, a tampered audit trail shown and verified without a traceback,
and typed errors from `serve` and `sign --sdk`."""

from __future__ import annotations

import asyncio
import json
import shutil
import socket
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from click.testing import CliRunner
from cryptography.hazmat.primitives.asymmetric import ed25519, mldsa
from rcan.signing import MLDSAKeyPair
from starlette.applications import Starlette

from antireplay.audit import AuditLog, verify
from antireplay.cli import main
from antireplay.cli._common import importable_cwd
from antireplay.cli.demo import JSON, command, load_operator_key, write_demo_config
from antireplay.config import AppConfig
from antireplay.core.clock import Clock, ManualClock
from antireplay.core.errors import StateUnavailableError
from antireplay.http.gateway import create_app, embedded_default
from antireplay.rcan.auth import write_key_pair
from tests.audit.test_audit import sql, trail
from tests.cli.test_cli import one_line_error
from tests.conftest import ROOT
from tests.harness import free_port
from tests.redis_server import RedisServer

#: The default skew_s: a new deployment's fence refuses messages stamped up to this after it.
SKEW_S = 5.0


def call(app: Starlette, method: str, path: str, content: bytes | None = None) -> httpx.Response:
    """One request to the app in process (ASGI, no socket)."""

    async def once() -> httpx.Response:
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://gateway") as http:
            return await http.request(method, path, content=content, headers=JSON)

    return asyncio.run(once())


@contextmanager
def gateway(state: Path, clock: Clock | None = None, **overrides: str) -> Iterator[Starlette]:
    """The demo gateway in process; its store closed afterwards."""
    app = create_app(AppConfig.from_yaml(write_demo_config(state, **overrides)), clock=clock)
    try:
        yield app
    finally:
        app.state.receiver.cache.store.close()


def send(app: Starlette, state: Path, age_s: float = 0.0) -> httpx.Response:
    return call(app, "POST", "/v1/messages", command(load_operator_key(state), age_s))


def test_readyz_is_503_when_redis_may_evict_and_so_is_a_command(tmp_path: Path) -> None:
    server = RedisServer(tmp_path)
    server.start()
    try:
        clock = ManualClock(wall=time.time())
        with gateway(tmp_path, clock, store=server.url) as app:  # a new deployment: fenced
            clock.advance(SKEW_S + 1)  # messages stamped this far ahead pass that fence
            assert call(app, "GET", "/readyz").status_code == 200
            server.client().config_set("maxmemory-policy", "allkeys-lru")
            probe = call(app, "GET", "/readyz")
            assert probe.status_code == 503, probe.text
            assert "maxmemory-policy allkeys-lru" in probe.json()["reason"]
            refused = send(app, tmp_path, -(SKEW_S + 1))
            assert (refused.status_code, refused.json()["code"]) == (503, "STATE_UNAVAILABLE")
            server.client().config_set("maxmemory-policy", "noeviction")
            assert call(app, "GET", "/readyz").status_code == 200
            assert send(app, tmp_path, -(SKEW_S + 1)).status_code == 200
    finally:
        server.stop()


def test_readyz_is_503_while_another_process_holds_the_state_write_lock(tmp_path: Path) -> None:
    with gateway(tmp_path, store=f"sqlite:{tmp_path / 'state.db'}") as app:
        assert call(app, "GET", "/readyz").status_code == 200
        holder = sqlite3.connect(tmp_path / "state.db", timeout=0)
        holder.execute("BEGIN IMMEDIATE")
        try:
            blocked = call(app, "GET", "/readyz")
        finally:
            holder.execute("ROLLBACK")
            holder.close()
        assert blocked.status_code == 503
        assert blocked.json()["reason"].endswith("state.db: database is locked")
        assert call(app, "GET", "/readyz").status_code == 200
        assert send(app, tmp_path).status_code == 200


def test_a_deleted_state_file_stays_missing_and_unready_and_commands_are_refused(
    tmp_path: Path,
) -> None:
    db = tmp_path / "state.db"
    with gateway(tmp_path) as app:
        assert send(app, tmp_path).status_code == 200  # readers and the writer are open
        assert call(app, "GET", "/readyz").status_code == 200
        shutil.copy(db, tmp_path / "copy.db")
        db.unlink()
        for restored in (False, False, True):  # then a copy put in its place: still refused
            if restored:
                shutil.copy(tmp_path / "copy.db", db)
            probe = call(app, "GET", "/readyz")
            assert probe.status_code == 503, probe.text
            assert "deleted or replaced while running" in probe.json()["reason"]
            refused = send(app, tmp_path)
            assert (refused.status_code, refused.json()["code"]) == (503, "STATE_UNAVAILABLE")
            metrics = call(app, "GET", "/metrics")
            assert metrics.status_code == 200
            assert db.exists() is restored  # no probe, lookup or scrape made a new database


# --- audit tail and verify on what a trail holds ------------------------------------------------

REASON = "database missing, truncated or replaced (the witness says it existed)"


def lost_and_found(path: Path, reason: str) -> None:
    """A STATE_LOST row (its warning is the store's reason, free text) and a row with no
    sender (a memo hit)."""
    log = AuditLog(path)
    log.append(at=1_800_000_000.0, outcome="state", code="STATE_LOST", warning=reason,
               msg_type=None, sender=None, sender_verified=False, msg_id=None)  # fmt: skip
    log.append(at=1_800_000_001.0, outcome="rejected", code="REPLAY_DETECTED", warning=None,
               msg_type=1, sender=None, sender_verified=False, msg_id="m1")  # fmt: skip
    log.close()


def tail_json(path: Path) -> list[dict[str, Any]]:
    result = CliRunner().invoke(main, ["audit", "tail", str(path), "--json"])
    assert result.exit_code == 0, result.output
    return [json.loads(line) for line in result.output.splitlines()]


def test_audit_tail_shows_the_state_lost_reason_and_no_none_sender(tmp_path: Path) -> None:
    path = tmp_path / "audit.db"
    lost_and_found(path, REASON)
    lost, memo = tail_json(path)
    assert lost["warning"] == REASON
    table = CliRunner().invoke(main, ["audit", "tail", str(path)])
    assert table.exit_code == 0, table.output
    assert REASON in table.output
    assert "None" not in table.output  # a row without a sender shows "-"
    assert memo["sender"] is None


def test_audit_tail_escapes_and_bounds_a_hostile_reason(tmp_path: Path) -> None:
    path = tmp_path / "audit.db"
    lost_and_found(path, "lost\x1b[2J\nforged line\u202e" + "x" * 500)
    (lost, _) = tail_json(path)
    shown = lost["warning"]
    assert shown.startswith("lost\\x1b[2J\\nforged line\\u202e") and len(shown) == 200
    assert shown.isprintable()
    table = CliRunner().invoke(main, ["audit", "tail", str(path)])
    assert "\x1b" not in table.output and "forged line" in table.output


@pytest.mark.parametrize("at", ["1e300", "9e999", "-9e999", "-5", "'yesterday'", "x'00'"])
def test_a_tampered_time_or_type_is_shown_invalid_and_verify_names_the_row(
    tmp_path: Path, at: str
) -> None:
    path = tmp_path / "audit.db"
    trail(path, 3)
    sql(path, f"UPDATE audit SET at = {at}, msg_type = 'x\x1b[31m<b>' || char(10) WHERE seq = 2")
    for args in (["--json"], []):
        result = CliRunner().invoke(main, ["audit", "tail", str(path), *args])
        assert result.exit_code == 0, result.output
        assert "Traceback" not in result.output and "\x1b" not in result.output
        assert "<b>" not in result.output  # the hostile type is hashed like any identifier
    rows = tail_json(path)
    assert (rows[1]["at"], rows[1]["time"]) == (None, "invalid")
    assert rows[1]["msg_type"].startswith("sha256:")
    assert rows[0]["time"] == "2027-01-15T08:00:00Z"  # its neighbours are intact
    report = verify(path)
    assert (report.broken_at, report.reason) == (2, "invalid at: a value antireplay never writes")
    result = CliRunner().invoke(main, ["audit", "verify", str(path)])
    assert result.exit_code == 1 and "chain broken at row 2: invalid at" in result.output


def test_verify_names_a_blob_in_a_text_column(tmp_path: Path) -> None:
    path = tmp_path / "audit.db"
    trail(path, 2)
    sql(path, "UPDATE audit SET sender = x'ff00' WHERE seq = 1")
    assert (verify(path).broken_at, verify(path).reason) == (
        1, "invalid sender: a value antireplay never writes",
    )  # fmt: skip
    assert CliRunner().invoke(main, ["audit", "tail", str(path)]).exit_code == 0


# --- serve: the working directory, TLS; mavlink-router --metrics-host -------------------------


def test_the_working_directory_goes_on_sys_path_only_for_a_module_upstream(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    for upstream in (None, "http://robot:8000/cmd", "https://robot/cmd"):
        importable_cwd(upstream)
        assert str(tmp_path) not in sys.path, upstream
    config = yaml.safe_load(write_demo_config(tmp_path).read_text())
    with socket.socket() as robot:  # config check connects to an HTTP upstream: one listens
        robot.bind(("127.0.0.1", 0))
        robot.listen()
        http = f"http://127.0.0.1:{robot.getsockname()[1]}/x"
        for upstream, added in ((http, False), ("antireplay.cli.demo:robot", True)):
            (tmp_path / "c.yaml").write_text(yaml.safe_dump({**config, "upstream": upstream}))
            result = CliRunner().invoke(main, ["config", "check", str(tmp_path / "c.yaml")])
            assert result.exit_code == 0, result.output
            assert (str(tmp_path) in sys.path) is added, upstream


def test_a_bad_tls_certificate_or_key_is_one_line_naming_both(tmp_path: Path) -> None:
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    cert.write_text("not a certificate\n")
    key.write_text("not a key\n")
    args = ["serve", "--state-dir", str(tmp_path / "state"), "--port", "0"]
    result = CliRunner().invoke(
        main, [*args, "--ssl-certfile", str(cert), "--ssl-keyfile", str(key)]
    )
    one_line_error(result, "--ssl-certfile", str(cert), "--ssl-keyfile", str(key), "PEM")


@pytest.mark.parametrize(("host", "why"), [("192.0.2.1", "assign"), ("bad..host", "label")])
def test_mavlink_router_metrics_host_errors_name_the_option(
    tmp_path: Path, host: str, why: str
) -> None:
    key = tmp_path / "link.key"
    key.write_bytes(bytes(range(32)))
    args = ["mavlink-proxy", "--forward", "udp:127.0.0.1:9", "--key-file", str(key),
            "--audit", str(tmp_path / "audit.db"), "--store", "memory",
            "--listen", f"udp:127.0.0.1:{free_udp_port()}",
            "--metrics-port", str(free_port()), "--metrics-host", host]  # fmt: skip
    script = Path(sys.executable).with_name("antireplay")  # a process: metrics are global
    done = subprocess.run([script, *args], capture_output=True, text=True, timeout=60, check=False)
    assert (done.returncode, done.stdout) == (2, ""), done.stderr
    (line,) = done.stderr.splitlines()
    assert line.startswith("antireplay: error: --metrics-host " + host) and why in line, line


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


# --- sign --sdk ---------------------------------------------------------------------------------

ROBOT = "rcan://registry.rcan.dev/acme/arm/v2/unit-001"


def sdk_sign(key: Path, *extra: str) -> Any:
    return CliRunner().invoke(main, ["sign", "--sdk", "--key", str(key), "--cmd", "c", *extra])


def test_sign_sdk_without_the_sdks_ml_dsa_is_one_line_naming_the_install(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    MLDSAKeyPair.generate().save(tmp_path / "sdk.key")
    monkeypatch.setitem(sys.modules, "dilithium_py", None)  # as if rcan[pq] were missing
    monkeypatch.setitem(sys.modules, "dilithium_py.ml_dsa", None)
    result = sdk_sign(tmp_path / "sdk.key", "--target", ROBOT)
    one_line_error(result, "--key", "sdk.key", "pip install 'rcan[pq]'")


def test_sign_sdk_key_errors_name_the_file_and_what_is_accepted(tmp_path: Path) -> None:
    damaged = tmp_path / "damaged.key"
    damaged.write_bytes(b"MLDS\x00\x05" + b"x" * 40)
    write_key_pair(ed25519.Ed25519PrivateKey.generate(), tmp_path / "ed.pem", tmp_path / "ed.pub")
    (tmp_path / "junk.pem").write_text("junk")
    for name, needle in (("damaged.key", "damaged"), ("ed.pem", "ML-DSA-65 only"),
                         ("junk.pem", "not an unencrypted PEM")):  # fmt: skip
        line = one_line_error(sdk_sign(tmp_path / name, "--target", ROBOT), name, needle)
        assert "accepted" in line or "RCAN SDK key file" in line, line
        assert "safety message" not in line  # no hint about ESTOP on a key error


def test_sign_sdk_hints_at_safety_only_for_unsigned_safety_fields(tmp_path: Path) -> None:
    write_key_pair(mldsa.MLDSA65PrivateKey.generate(), tmp_path / "k.pem", tmp_path / "k.pub")
    bad = tmp_path / "m.json"
    bad.write_text(json.dumps({"params": "not an object", "target": ROBOT}))
    line = one_line_error(sdk_sign(tmp_path / "k.pem", "--json", str(bad)), "params")
    assert "safety message" not in line
    line = one_line_error(sdk_sign(tmp_path / "k.pem", "--target", ROBOT, "--type", "6"), "type")
    assert "ESTOP/STOP/RESUME is a safety message" in line


@pytest.mark.parametrize("target", ["t", "rcan://registry/acme/arm/v2", "rcan://r/a/m/v/d e"])
def test_sign_sdk_refuses_a_target_the_sdk_cannot_parse(tmp_path: Path, target: str) -> None:
    write_key_pair(mldsa.MLDSA65PrivateKey.generate(), tmp_path / "k.pem", tmp_path / "k.pub")
    one_line_error(sdk_sign(tmp_path / "k.pem", "--target", target), "target", "RCAN SDK")
    one_line_error(sdk_sign(tmp_path / "k.pem"), "target", "missing")


# --- metrics and the README ---------------------------------------------------------------------


def test_metrics_counters_keep_their_last_value_while_the_store_is_down(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    app = create_app(embedded_default(tmp_path))
    loss = 'antireplay_state_data_loss_total{backend="sqlite"}'
    assert f"{loss} 0.0" in call(app, "GET", "/metrics").text

    def down() -> dict[str, float]:
        raise StateUnavailableError("sqlite: down")

    monkeypatch.setattr(app.state.receiver.cache.store, "status", down)
    text = call(app, "GET", "/metrics").text
    assert (
        f"{loss} 0.0" in text and 'antireplay_watermark_raises_total{backend="sqlite"} 0.0' in text
    )
    assert 'antireplay_cache_entries{backend="sqlite"} NaN' in text  # a gauge may be unknown
    counters = [line for line in text.splitlines() if "_total{" in line]
    assert counters and not any(line.endswith("NaN") for line in counters), counters


def test_readme_waits_for_readiness_in_bounded_loops_and_notes_the_upgrade() -> None:
    readme = (ROOT / "README.md").read_text()
    assert "until curl" not in readme
    assert readme.count("for i in $(seq 100); do curl -sf") == 2
    assert "**Upgrading:** a signed `cmd` `STOP` or `RESUME` is now SAFETY" in readme
