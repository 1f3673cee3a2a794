"""``antireplay keygen``, ``sign`` and ``send``: what ``sign --sdk`` refuses, each as one line
naming the input; secrets written mode 0600 and a warning for a shared one; ``send --json``."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner, Result
from cryptography.hazmat.primitives.asymmetric import ed25519, mldsa
from rcan.signing import MLDSAKeyPair

from antireplay.cli import main
from antireplay.cli.demo import command, load_operator_key, write_demo_config
from antireplay.rcan.auth import write_key_pair
from harness import antireplay, one_line_error, serving
from harness.stores import aged_state

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
