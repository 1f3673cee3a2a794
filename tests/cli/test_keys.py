"""``antireplay keygen``, ``sign`` and ``send``: what ``sign --sdk`` refuses, each as one line
naming the input; secrets written mode 0600 and a warning for a shared one; ``send --json``.
``keys revoke|unrevoke|list|reload`` and key validity periods on real ``serve`` processes
(two replicas on one Redis, one SQLite host, a SIGHUP reload under wrk)."""

from __future__ import annotations

import json
import os
import re
import signal
import sys
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import httpx
import pytest
import yaml
from click.testing import CliRunner, Result
from cryptography.hazmat.primitives.asymmetric import ed25519, mldsa
from rcan.signing import MLDSAKeyPair

from antireplay.audit import AuditLog
from antireplay.cli import main
from antireplay.cli.demo import command, load_operator_key, write_demo_config
from antireplay.rcan.auth import write_key_pair
from harness import (
    GatewayProcess,
    antireplay,
    metric,
    one_line_error,
    post,
    serving,
    signed_by,
    until,
)
from harness.redis_server import RedisServer
from harness.stores import aged_state
from harness.wrk import WrkLoad

ROBOT = "rcan://registry.rcan.dev/acme/arm/v2/unit-001"


def sdk_sign(key: Path, *extra: str) -> Result:
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


def test_secrets_are_written_0600_and_a_shared_one_is_warned_about(tmp_path: Path) -> None:
    """``keygen`` writes private keys and a fleet PSK mode 0600 (never over an existing
    one); ``sign`` reading a key that group or others may read warns in one line."""
    made = antireplay("keygen", "--alg", "psk", "--out", "fleet", cwd=tmp_path)
    assert made.returncode == 0, made.stderr
    assert len(bytes.fromhex((tmp_path / "fleet.psk").read_text())) == 32
    again = antireplay("keygen", "--alg", "psk", "--out", "fleet", cwd=tmp_path)
    assert again.returncode == 2 and "refusing to overwrite" in again.stderr
    assert antireplay("keygen", "--out", "operator", cwd=tmp_path).returncode == 0
    for secret in ("fleet.psk", "operator.key.pem"):
        assert (tmp_path / secret).stat().st_mode & 0o777 == 0o600, secret
    sign = ("sign", "--key", "operator.key.pem", "--kid", "operator", "--cmd", "c",
            "--target", ROBOT)  # fmt: skip
    quiet = antireplay(*sign, cwd=tmp_path)
    assert quiet.returncode == 0 and quiet.stderr == "", quiet.stderr
    os.chmod(tmp_path / "operator.key.pem", 0o644)
    loud = antireplay(*sign, cwd=tmp_path)
    assert loud.returncode == 0 and json.loads(loud.stdout)["sig"]["kid"] == "operator"
    assert loud.stderr.splitlines() == [
        "antireplay: warning: --key operator.key.pem is open to group or others (mode 0644); "
        "keep a secret mode 0600: chmod 600 operator.key.pem"
    ]


def test_send_json_is_one_object_with_status_code_reason_and_body(tmp_path: Path) -> None:
    config = write_demo_config(tmp_path)
    (tmp_path / "msg.json").write_bytes(command(load_operator_key(tmp_path)))
    aged_state(tmp_path / "state.db")  # history: no first start's fence
    with serving(config) as gateway:
        first = antireplay("send", "--json", gateway.url, "msg.json", cwd=tmp_path)
        again = antireplay("send", "--json", gateway.url, "msg.json", cwd=tmp_path)
    accepted, refused = json.loads(first.stdout), json.loads(again.stdout)
    assert first.returncode == 0 and again.returncode == 1, (first.stderr, again.stderr)
    assert (accepted["status"], accepted["code"], accepted["reason"]) == (200, None, None)
    assert accepted["body"]["accepted"] is True
    assert accepted["sent_as"] == "sent cmd move_forward as COMMAND"
    assert (refused["status"], refused["code"]) == (409, "REPLAY_DETECTED")
    assert refused["reason"].startswith("REPLAY_DETECTED: ") and refused["body"]["type"] == 18


# --- keys revoke / unrevoke / reload, and key validity periods, on real gateways ------------


def _code(gateway: GatewayProcess, raw: bytes) -> str | None:
    reply = post(gateway, raw)
    return None if reply.status_code == 200 else reply.json()["code"]


def _revoke_reaches(gateway: GatewayProcess, key: ed25519.Ed25519PrivateKey, *cli: str) -> float:
    """Run ``antireplay keys revoke operator CLI...``; seconds from its return until
    ``gateway`` refuses the key (polled with a deadline, never slept)."""
    done = antireplay("keys", "revoke", "operator", *cli, cwd=Path.cwd())
    returned = time.monotonic()
    assert done.returncode == 0, done.stderr
    until("the revocation to reach the gateway", lambda: _code(gateway, command(key)), 10)
    took = time.monotonic() - returned
    assert _code(gateway, command(key)) == "KEY_REVOKED"
    return took


def test_a_revoke_on_one_redis_replica_reaches_the_other_within_one_second(
    tmp_path: Path,
) -> None:
    """Two ``serve`` processes on one Redis: ``keys revoke`` (pointed at the same config)
    and the other replica refuses the key (401 KEY_REVOKED, a NACK, counted, audited)
    within 1 s of the command's return; ``keys unrevoke`` lets it in again."""
    server = RedisServer(tmp_path)
    server.start()
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state, store=server.url)
    key = load_operator_key(state)
    a, b = GatewayProcess(config), GatewayProcess(config)
    try:
        a.start()
        b.start()
        assert _code(b, command(key)) is None
        took = _revoke_reaches(b, key, "--config", str(config))
        assert took <= 1.0, f"the revocation took {took:.3f} s to reach the other replica"
        # a polls on its own 0.25 s cycle: it may lag b by one poll (within the same promise)
        until("the revocation to reach the first replica", lambda: _code(a, command(key)), 1)
        assert _code(a, command(key)) == "KEY_REVOKED"
        assert metric(b, "antireplay_rejected_total", '{code="KEY_REVOKED"}') >= 1
        assert metric(b, "antireplay_keys_revoked") == 1
        listed = antireplay("keys", "list", "--config", str(config), cwd=tmp_path)
        assert listed.stdout.split() == ["operator"]
        undone = antireplay("keys", "unrevoke", "operator", "--config", str(config), cwd=tmp_path)
        assert undone.returncode == 0, undone.stderr
        until("the unrevoke to reach the gateway", lambda: _code(a, command(key)) is None, 10)
    finally:
        a.stop()
        b.stop()
        server.stop()
    rows = AuditLog(state / "audit.db").tail(500)
    changes = [(r.code, r.warning) for r in rows if r.outcome == "keys"]
    assert changes == [("KEY_REVOKE", "kid=operator"), ("KEY_UNREVOKE", "kid=operator")]
    refused = [r for r in rows if r.code == "KEY_REVOKED"]
    assert refused and all(r.sender == "kid:operator" and not r.sender_verified for r in refused)


def test_a_revoke_on_a_sqlite_state_reaches_its_gateway_within_one_second(tmp_path: Path) -> None:
    """One host: the revocation list sits beside the SQLite state (``--store``/``--audit``
    name it as the gateway's config does)."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    key = load_operator_key(state)
    with serving(config) as gateway:
        assert _code(gateway, command(key)) is None
        store, audit = f"sqlite:{state / 'state.db'}", str(state / "audit.db")
        took = _revoke_reaches(gateway, key, "--store", store, "--audit", audit)
        assert took <= 1.0, f"the revocation took {took:.3f} s to reach the gateway"
    assert (state / "state.revocations.db").exists()


def _expiry(gateway: GatewayProcess, kid: str) -> float:
    text = httpx.get(f"{gateway.url}/metrics", timeout=10).text
    found = re.search(rf'^antireplay_key_expiry_seconds{{kid="{kid}"}} (\S+)$', text, re.M)
    assert found is not None, text
    return float(found.group(1))


def test_keys_outside_their_validity_period_are_refused_with_their_own_codes(
    tmp_path: Path,
) -> None:
    """``not_after`` past: 401 KEY_EXPIRED; ``not_before`` ahead: 401 KEY_NOT_YET_VALID; the
    expiry metric per kid; ``config check`` warns of the expired key and of one within
    14 days."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    key = load_operator_key(state)
    now = datetime.now(timezone.utc)
    base = yaml.safe_load(config.read_text())
    operator = base["keys"][0]
    base["keys"] = [
        {**operator, "not_after": (now - timedelta(hours=1)).isoformat()},
        {**operator, "kid": "soon", "not_after": (now + timedelta(days=3)).isoformat()},
        {**operator, "kid": "later", "not_before": (now + timedelta(days=1)).isoformat()},
    ]
    config.write_text(yaml.safe_dump(base))
    checked = antireplay("config", "check", str(config), cwd=tmp_path)
    assert checked.returncode == 0, checked.stderr
    assert "keys.operator expired" in checked.stderr
    assert "keys.soon expires in 3.0 days" in checked.stderr
    with serving(config) as gateway:
        assert _code(gateway, command(key)) == "KEY_EXPIRED"
        assert _code(gateway, signed_by(key, "later")) == "KEY_NOT_YET_VALID"
        assert _code(gateway, signed_by(key, "soon")) is None
        assert _expiry(gateway, "operator") < 0 < _expiry(gateway, "soon") <= 3 * 86400
        assert metric(gateway, "antireplay_rejected_total", '{code="KEY_EXPIRED"}') == 1
    codes = {r.code for r in AuditLog(state / "audit.db").tail(50)}
    assert {"KEY_EXPIRED", "KEY_NOT_YET_VALID"} <= codes


def test_sighup_reloads_a_rotated_key_while_wrk_runs_and_drops_no_request(
    tmp_path: Path,
) -> None:
    """A rotation: the new key (a second kid of the same owner) is added to the file and
    ``serve`` gets SIGHUP while wrk sends old-key commands: the new key is accepted after
    the reload, and every wrk answer is 200 (each command once) or 409 (its replays), with
    no socket error.  A file that no longer parses then keeps the keys (one log line)."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    key = load_operator_key(state)
    new = ed25519.Ed25519PrivateKey.generate()
    write_key_pair(new, state / "next.key.pem", state / "next.pub.pem")
    written = yaml.safe_load(config.read_text())
    rotated = {
        **written["keys"][0],
        "kid": "operator-2",
        "public_keys": [str(state / "next.pub.pem")],
    }
    with serving(config) as gateway:
        assert gateway.proc is not None
        bodies = [command(key) for _ in range(200)]  # stamped after the first start's fence
        assert _code(gateway, signed_by(new, "operator-2")) == "UNKNOWN_SENDER"
        load = WrkLoad(gateway.url, bodies, tmp_path, seconds=4)
        until("wrk to be under way", lambda: metric(gateway, "antireplay_accepted_total") >= 20)
        config.write_text(yaml.safe_dump({**written, "keys": [*written["keys"], rotated]}))
        gateway.proc.send_signal(signal.SIGHUP)
        until(
            "the new key to be accepted",
            lambda: _code(gateway, signed_by(new, "operator-2")) is None,
        )
        run = load.result()
        assert run.socket_errors == 0, run
        # wrk sends the bodies in order, then their replays: each one it sent accepted once
        assert set(run.statuses) <= {200, 409}, run
        assert run.statuses[200] == min(len(bodies), run.requests), run
        assert sum(run.statuses.values()) == run.requests
        config.write_text("keys: [oops\n")
        gateway.proc.send_signal(signal.SIGHUP)
        until(
            "the bad reload",
            lambda: metric(gateway, "antireplay_key_reloads_total", '{result="failed"}'),
        )
        assert _code(gateway, signed_by(new, "operator-2")) is None
        assert metric(gateway, "antireplay_key_reloads_total", '{result="ok"}') == 1
    failed = [ln for ln in (gateway.stderr_text or "").splitlines() if "reload failed" in ln]
    assert len(failed) == 1 and "keeping the 2 loaded keys" in failed[0]


def test_a_revoked_key_is_refused_under_its_second_kid_and_config_check_warns(
    tmp_path: Path,
) -> None:
    """One public key under two kids: ``config check`` warns, and ``keys revoke`` of one
    kid refuses the key under the other too (the signer picks ``sig.kid``)."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    key = load_operator_key(state)
    base = yaml.safe_load(config.read_text())
    base["keys"].append({**base["keys"][0], "kid": "operator-2"})
    config.write_text(yaml.safe_dump(base))
    checked = antireplay("config", "check", str(config), cwd=tmp_path)
    assert "keys.operator-2 and keys.operator are one public key" in checked.stderr
    with serving(config) as gateway:
        assert _code(gateway, signed_by(key, "operator-2")) is None
        _revoke_reaches(gateway, key, "--config", str(config))
        assert _code(gateway, signed_by(key, "operator-2")) == "KEY_REVOKED"


@pytest.mark.parametrize(
    ("kid", "needle"),
    [
        (os.fsdecode(b"\xff"), "valid UTF-8"),
        ("a\nb", "no whitespace or control"),
        ("op erator", "no whitespace or control"),
        ("k" * 129, "at most 128"),
    ],
    ids=["not-utf8", "newline", "space", "too-long"],
)
def test_keys_revoke_refuses_a_kid_outside_the_config_grammar(
    tmp_path: Path, kid: str, needle: str
) -> None:
    """One line, exit 2, nothing stored (a newline kid would read as two in ``keys list``)."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    done = antireplay("keys", "revoke", "--config", str(config), "--force", kid, cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("antireplay: error: kid ") and needle in done.stderr
    assert len(done.stderr.splitlines()) == 1 and "Traceback" not in done.stderr
    listed = antireplay("keys", "list", "--config", str(config), cwd=tmp_path)
    assert listed.returncode == 0 and listed.stdout == ""


def test_keys_revoke_refuses_a_kid_the_config_does_not_name_and_a_memory_store(
    tmp_path: Path,
) -> None:
    """A case variant or a typo exits 2 naming the near match (the key stays trusted, so a
    success line would lie); ``--force`` revokes it (before deployment); ``--store memory``
    reaches no gateway."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    for kid, near in (("Operator", "operator"), ("operatr", "operator")):
        done = antireplay("keys", "revoke", "--config", str(config), kid, cwd=tmp_path)
        assert done.returncode == 2, done.stderr
        assert f"did you mean {near}?" in done.stderr and "--force" in done.stderr
        assert len(done.stderr.splitlines()) == 1
    forced = antireplay(
        "keys", "revoke", "--config", str(config), "--force", "next-op", cwd=tmp_path
    )
    assert forced.returncode == 0, forced.stderr
    listed = antireplay("keys", "list", "--config", str(config), cwd=tmp_path)
    assert listed.stdout.split() == ["next-op"]
    audit = str(tmp_path / "x.db")
    memory = antireplay(
        "keys", "revoke", "--store", "memory", "--audit", audit, "operator", cwd=tmp_path
    )
    assert memory.returncode == 2 and "store memory" in memory.stderr
    assert len(memory.stderr.splitlines()) == 1


def test_a_revoke_whose_audit_row_fails_says_the_key_is_revoked(tmp_path: Path) -> None:
    """The list changed, only the row did not: exit 1 with the truth, never an error that
    reads as if the revoke (or the unrevoke) had not happened."""
    state = tmp_path / "state"
    state.mkdir()
    (tmp_path / "afile").write_text("")
    store, audit = f"sqlite:{state / 'state.db'}", str(tmp_path / "afile" / "audit.db")
    for verb in ("revoke", "unrevoke"):
        done = antireplay(
            "keys", verb, "--store", store, "--audit", audit, "operator", cwd=tmp_path
        )
        assert done.returncode == 1, done.stderr
        assert f"{verb}d operator on sqlite:" in done.stderr
        assert "its audit row could not be written" in done.stderr
        listed = antireplay("keys", "list", "--store", store, cwd=tmp_path)
        assert listed.stdout.split() == (["operator"] if verb == "revoke" else [])
