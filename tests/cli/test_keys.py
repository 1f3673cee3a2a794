"""``antireplay sign --sdk``: what it refuses, each as one line naming the input."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner, Result
from cryptography.hazmat.primitives.asymmetric import ed25519, mldsa
from rcan.signing import MLDSAKeyPair

from antireplay.cli import main
from antireplay.rcan.auth import write_key_pair
from harness import one_line_error

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
