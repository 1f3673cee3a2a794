"""``sign --key pkcs11:...``: an envelope signed by an Ed25519 key in a real SoftHSMv2
token is accepted by a gateway holding the public key; a token that is missing or locked
(wrong PIN, no such token or object, no module) is one line and exit 2, on the real CLI."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner
from cryptography.hazmat.primitives import serialization

import antireplay.keys
from antireplay.audit import AuditLog, AuditRow
from antireplay.cli import main
from antireplay.cli.demo import command, load_operator_key, write_demo_config
from harness import one_line_error, post, serving
from harness.softhsm import SoftToken, make_token
from harness.stores import aged_state

ROBOT = "rcan://registry.rcan.dev/acme/arm/v2/unit-001"


@pytest.fixture
def token(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> SoftToken:
    monkeypatch.delenv("SOFTHSM2_CONF", raising=False)
    made = make_token(tmp_path)
    monkeypatch.setenv("SOFTHSM2_CONF", str(made.conf))
    return made


def cli(token: SoftToken, *args: str, cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    """``antireplay ARGS`` in its own process, finding the token as an operator's shell would."""
    return subprocess.run(
        [sys.executable, "-m", "antireplay", *args], cwd=cwd, env=token.env(**env),
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip


def sign_with(
    token: SoftToken, key: str, tmp_path: Path, **env: str
) -> subprocess.CompletedProcess[str]:
    return cli(token, "sign", "--key", key, "--kid", "operator", "--cmd", "move_forward",
               "--target", ROBOT, "--param", "distance_m=0.5", cwd=tmp_path, **env)  # fmt: skip


def test_a_token_signed_envelope_is_accepted_by_the_gateway(
    token: SoftToken, tmp_path: Path
) -> None:
    public = token.generate_ed25519("operator")
    config = write_demo_config(tmp_path)
    (tmp_path / "operator.pub.pem").write_bytes(public.public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo))  # fmt: skip
    signed = sign_with(token, token.uri("operator"), tmp_path)
    assert signed.returncode == 0, signed.stderr
    assert json.loads(signed.stdout)["sig"]["alg"] == "ed25519"
    (tmp_path / "msg.json").write_text(signed.stdout)
    aged_state(tmp_path / "state.db")
    with serving(config) as gateway:
        sent = cli(token, "send", "--json", gateway.url, "msg.json", cwd=tmp_path)
    assert sent.returncode == 0, sent.stdout + sent.stderr
    assert json.loads(sent.stdout)["body"]["accepted"] is True


def test_the_pin_comes_from_a_pin_source_file_or_the_environment(
    token: SoftToken, tmp_path: Path
) -> None:
    token.generate_ed25519("operator")
    (tmp_path / "pin").write_text(token.pin + "\n")
    from_file = sign_with(
        token, token.uri("operator", pin="", query=f"pin-source=file:{tmp_path / 'pin'}"), tmp_path
    )
    from_env = sign_with(
        token, token.uri("operator", pin=""), tmp_path, ANTIREPLAY_PKCS11_PIN=token.pin
    )
    assert (from_file.returncode, from_env.returncode) == (0, 0), from_file.stderr + from_env.stderr


@pytest.mark.parametrize(
    ("key", "env", "needle"),
    [
        ("pkcs11:token=antireplay-test;object=operator?pin-value=0000", {}, "wrong or locked PIN"),
        ("pkcs11:token=nosuch;object=operator?pin-value=4321", {}, "no such token"),
        ("pkcs11:token=antireplay-test;object=nosuch?pin-value=4321", {}, "no such object"),
        ("pkcs11:token=antireplay-test;object=operator", {}, "no PIN"),
        ("pkcs11:token=antireplay-test;objet=operator", {}, "unknown path attribute 'objet'"),
        ("pkcs11:token=antireplay-test;object=operator?pin-value=4321",
         {"ANTIREPLAY_PKCS11_MODULE": "/nonexistent/libp11.so"}, "module /nonexistent/libp11.so"),
    ],
    ids=["wrong-pin", "no-token", "no-object", "no-pin", "typo", "no-module"],
)  # fmt: skip
def test_a_token_that_cannot_sign_is_one_line_and_exit_2(
    token: SoftToken, tmp_path: Path, key: str, env: dict[str, str], needle: str
) -> None:
    token.generate_ed25519("operator")
    done = sign_with(token, key, tmp_path, **env)
    assert done.returncode == 2 and done.stdout == "", done.stdout + done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("antireplay: error: --key pkcs11:"), done.stderr
    assert needle in lines[0] and "4321" not in lines[0], lines[0]


def test_the_audit_head_key_in_a_token_macs_the_trail_and_audit_verify_uses_it(
    token: SoftToken, tmp_path: Path
) -> None:
    token.import_secret("audit-mac", bytes(range(32)))
    uri = token.uri("audit-mac")
    audit = {"path": str(tmp_path / "audit.db"), "head_key": uri}
    config = write_demo_config(tmp_path, audit=audit)
    aged_state(tmp_path / "state.db")
    with serving(config) as gateway:
        for _ in range(3):
            assert post(gateway, command(load_operator_key(tmp_path))).status_code == 200
    assert not (tmp_path / "audit.db.key").exists()  # no key file: the token holds it
    proven = cli(token, "audit", "verify", "audit.db", "--head-key", uri, cwd=tmp_path)
    assert proven.returncode == 0, proven.stdout + proven.stderr
    assert "head checkpoint matches row 3 (MAC verified)" in proven.stdout, proven.stdout
    other = token.uri("other-mac")
    token.import_secret("other-mac", bytes(32))
    forged = cli(token, "audit", "verify", "audit.db", "--head-key", other, cwd=tmp_path)
    assert forged.returncode != 0, forged.stdout
    assert "does not verify" in forged.stdout + forged.stderr, forged.stdout + forged.stderr


def test_serve_with_a_locked_audit_token_is_one_line_and_exit_2(
    token: SoftToken, tmp_path: Path
) -> None:
    token.import_secret("audit-mac", bytes(range(32)))
    audit = {"path": str(tmp_path / "audit.db"), "head_key": token.uri("audit-mac", pin="0000")}
    config = write_demo_config(tmp_path, audit=audit)
    done = cli(token, "serve", "--config", str(config), "--port", "0", cwd=tmp_path)
    assert done.returncode == 2, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert lines[-1].startswith("antireplay: error: audit.head_key pkcs11:"), done.stderr
    assert "wrong or locked PIN" in lines[-1] and "Traceback" not in done.stderr, done.stderr


def test_reanchor_moves_a_trails_head_key_into_the_token(token: SoftToken, tmp_path: Path) -> None:
    """The operations runbook's move: a trail anchored with a key file, re-anchored under the
    token's key, then verifies with the token (and its segment links are MACed again)."""
    token.import_secret("audit-mac", bytes(range(32)))
    uri = token.uri("audit-mac")
    log = AuditLog(tmp_path / "audit.db")
    for i in range(3):
        log.append(AuditRow(at=1_800_000_000.0 + i, outcome="accepted", msg_type=1,
                            sender="operator", sender_verified=True, msg_id=f"m{i}"))  # fmt: skip
    log.close()
    before = cli(token, "audit", "verify", "audit.db", "--head-key", uri, cwd=tmp_path)
    assert before.returncode != 0 and "does not verify" in before.stdout + before.stderr
    moved = cli(token, "audit", "reanchor", "audit.db", "--head-key", uri, cwd=tmp_path)
    assert moved.returncode == 0, moved.stdout + moved.stderr
    after = cli(token, "audit", "verify", "audit.db", "--head-key", uri, cwd=tmp_path)
    assert after.returncode == 0 and "(MAC verified)" in after.stdout, after.stdout + after.stderr


def test_config_check_logs_in_to_the_audit_token(token: SoftToken, tmp_path: Path) -> None:
    token.import_secret("audit-mac", bytes(range(32)))
    for pin, code in ((token.pin, 0), ("0000", 2)):
        (tmp_path / pin).mkdir()
        audit = {"path": str(tmp_path / "audit.db"), "head_key": token.uri("audit-mac", pin=pin)}
        config = write_demo_config(tmp_path / pin, audit=audit)
        done = cli(token, "config", "check", str(config), cwd=tmp_path)
        assert done.returncode == code, done.stdout + done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith("antireplay: error: audit.head_key ")
    assert "wrong or locked PIN" in done.stderr and "Traceback" not in done.stderr


def test_an_audit_token_failing_while_serving_refuses_commands_and_passes_a_fresh_estop(
    token: SoftToken, tmp_path: Path
) -> None:
    """The token goes away under a running gateway (its directory removed: SoftHSMv2 then
    answers ObjectHandleInvalid): commands get 503 STATE_UNAVAILABLE, a fresh ESTOP whose
    signature verifies is delivered (warning AUDIT_UNAVAILABLE) and its row spilled.  A
    memory store: its audit rows are appended directly (a SQLite state's go to its outbox)."""
    token.import_secret("audit-mac", bytes(range(32)))
    audit = {"path": str(tmp_path / "audit.db"), "head_key": token.uri("audit-mac")}
    config = write_demo_config(tmp_path, audit=audit, store="memory")
    key = load_operator_key(tmp_path)
    with serving(config) as gateway:
        assert post(gateway, command(key)).status_code == 200
        shutil.rmtree(token.conf.parent / "softhsm-tokens")
        refused = post(gateway, command(key))
        estop = post(gateway, command(key, cmd="ESTOP", type=6, safety_event="ESTOP"))
    assert refused.status_code == 503 and refused.json()["code"] == "STATE_UNAVAILABLE", (
        refused.text
    )
    assert token.pin not in refused.text
    assert estop.status_code == 200 and estop.json()["warning"] == "AUDIT_UNAVAILABLE", estop.text
    assert "ESTOP delivered, its row spilled" in (gateway.stderr_text or "")


def test_without_python_pkcs11_a_token_key_is_one_line_naming_the_extra(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setitem(sys.modules, "antireplay.keys.pkcs11", None)  # import fails
    monkeypatch.delattr(antireplay.keys, "pkcs11", raising=False)
    result = CliRunner().invoke(main, ["sign", "--key", "pkcs11:token=t;object=o?pin-value=1",
                                       "--kid", "operator", "--cmd", "c"])  # fmt: skip
    one_line_error(result, "python-pkcs11 is not installed", "pip install 'antireplay[pkcs11]'")
    assert "pin-value=1" not in result.stderr


@pytest.mark.parametrize(
    "key",
    [
        "pkcs11:token=nope;object=x;pin-value=SECRET123",
        "pkcs11:token=antireplay-test;object=operator&pin-value=SECRET123",
        "PKCS11:token=antireplay-test;object=operator?pin-value=SECRET123",
    ],
    ids=["pin-in-path", "ampersand-typo", "upper-case-scheme"],
)
def test_a_malformed_uri_never_echoes_its_pin(token: SoftToken, tmp_path: Path, key: str) -> None:
    done = sign_with(token, key, tmp_path)
    assert done.returncode == 2, done.stderr
    assert "SECRET123" not in done.stderr + done.stdout and "pin-value=***" in done.stderr


def test_config_check_never_echoes_a_pin_in_the_audit_head_key(
    token: SoftToken, tmp_path: Path
) -> None:
    config = write_demo_config(tmp_path)
    data = yaml.safe_load(config.read_text())
    data["audit"] = {
        "path": data["audit"],
        "head_key": "pkcs11:token=nope;object=x;pin-value=SECRET99",
    }
    config.write_text(yaml.safe_dump(data))
    done = cli(token, "config", "check", str(config), cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert "SECRET99" not in done.stderr and "pin-value=***" in done.stderr


def test_a_pin_source_open_to_others_is_warned_about(token: SoftToken, tmp_path: Path) -> None:
    token.generate_ed25519("operator")
    pin = tmp_path / "pin"
    pin.write_text(token.pin + "\n")
    pin.chmod(0o644)
    done = sign_with(token, token.uri("operator", pin="", query=f"pin-source=file:{pin}"), tmp_path)
    assert done.returncode == 0, done.stderr
    assert f"pin-source {pin} is open to group or others (mode 0644)" in done.stderr
