"""The gateway wiring: the key registry built from the configuration."""

from __future__ import annotations

from pathlib import Path

import pytest
from cryptography.hazmat.primitives.asymmetric import ed25519

from antireplay.config import AppConfig, KeyConfig
from antireplay.core.errors import ConfigError
from antireplay.rcan.auth import write_key_pair
from antireplay.wiring import (
    build_registry,
)


def test_two_keys_under_one_kid_are_a_config_error(tmp_path: Path) -> None:
    """A kid names one key: a second entry would shadow the first (or leave it answering
    under an alias with its old scopes), and the audit could not tell which key signed."""
    entries = []
    for name, scopes in (("old", ["control", "safety"]), ("new", ["control"])):
        public = tmp_path / f"{name}.pub.pem"
        write_key_pair(ed25519.Ed25519PrivateKey.generate(), tmp_path / f"{name}.pem", public)
        key = KeyConfig(kid="operator", owner="op", alg="ed25519", public_keys=[str(public)],
                        scopes=scopes)  # fmt: skip
        entries.append(key)
    with pytest.raises(ConfigError, match=r"keys\.operator\.kid"):
        build_registry(AppConfig(keys=entries))
