"""Real SoftHSMv2 tokens for tests and benchmarks: one private token directory each
(``SOFTHSM2_CONF`` pointing at it), initialized with ``softhsm2-util``, keys imported or
generated through python-pkcs11.  Fails, never skips, when softhsm2 is not installed.

SoftHSMv2 reads ``SOFTHSM2_CONF`` and scans its token directory at ``C_Initialize``:
:func:`make_token` sets the variable in this process and re-initializes the module, so
in-process keys see the new token (and any session opened before is closed: a test's
way to make a token fail while serving)."""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pkcs11
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey
from pkcs11 import Attribute, KeyType, Mechanism, ObjectClass

from antireplay.keys.pkcs11 import DEFAULT_MODULE

#: Ed25519's curve as CKA_EC_PARAMS: the printable string "edwards25519" (SoftHSMv2 2.6 also
#: takes the OID 1.3.101.112; the name is what its docs use).
ED25519_PARAMS = bytes.fromhex("130c656477617264733235353139")


@dataclass(frozen=True)
class SoftToken:
    """One initialized token: its configuration, label and PINs."""

    conf: Path
    label: str
    pin: str
    so_pin: str

    def env(self, **extra: str) -> dict[str, str]:
        """The environment a CLI process needs to find this token."""
        return {**os.environ, "SOFTHSM2_CONF": str(self.conf), **extra}

    def uri(self, obj: str, *, pin: str | None = None, query: str = "") -> str:
        """``pkcs11:token=LABEL;object=OBJ?pin-value=PIN`` (``pin=""``: no PIN in it)."""
        pin = self.pin if pin is None else pin
        tail = "&".join(q for q in (f"pin-value={pin}" if pin else "", query) if q)
        return f"pkcs11:token={self.label};object={obj}" + (f"?{tail}" if tail else "")

    @contextmanager
    def session(self) -> Iterator[Any]:
        """A read-write user session on the token (this process)."""
        token = pkcs11.lib(DEFAULT_MODULE).get_token(token_label=self.label)
        with token.open(user_pin=self.pin, rw=True) as session:
            yield session

    def import_secret(self, label: str, value: bytes) -> None:
        """A generic secret (HMAC, digest) with a known value, sensitive, not extractable."""
        with self.session() as session:
            session.create_object({
                Attribute.CLASS: ObjectClass.SECRET_KEY, Attribute.KEY_TYPE: KeyType.GENERIC_SECRET,
                Attribute.TOKEN: True, Attribute.LABEL: label, Attribute.VALUE: value,
                Attribute.SIGN: True, Attribute.VERIFY: True, Attribute.SENSITIVE: True,
                Attribute.EXTRACTABLE: False,
            })  # fmt: skip

    def generate_ed25519(self, label: str) -> Ed25519PublicKey:
        """An Ed25519 key pair generated in the token; its public key."""
        with self.session() as session:
            public, _ = session.generate_keypair(
                KeyType.EC_EDWARDS, store=True, label=label, id=label.encode(),
                mechanism=Mechanism.EC_EDWARDS_KEY_PAIR_GEN,
                public_template={Attribute.EC_PARAMS: ED25519_PARAMS},
            )  # fmt: skip
            point = bytes(public[Attribute.EC_POINT])
        return Ed25519PublicKey.from_public_bytes(point[-32:])


def softhsm2_util() -> str:
    found = shutil.which("softhsm2-util")
    if found is None or not Path(DEFAULT_MODULE).exists():
        pytest.fail("softhsm2 is not installed (scripts/install-system-packages installs it)")
    return found


def make_token(root: Path, label: str = "antireplay-test", pin: str = "4321") -> SoftToken:
    """A fresh token in its own directory under ``root``; ``SOFTHSM2_CONF`` set to it here."""
    tokens = root / "softhsm-tokens"
    tokens.mkdir(parents=True, exist_ok=True)
    conf = root / "softhsm2.conf"
    conf.write_text(f"directories.tokendir = {tokens}\nobjectstore.backend = file\n"
                    "log.level = ERROR\nslots.removable = false\n")  # fmt: skip
    token = SoftToken(conf, label, pin, so_pin="87654321")
    os.environ["SOFTHSM2_CONF"] = str(conf)
    subprocess.run(
        [softhsm2_util(), "--init-token", "--free", "--label", label, "--so-pin", token.so_pin,
         "--pin", pin],
        env=token.env(), check=True, capture_output=True, timeout=30,
    )  # fmt: skip
    pkcs11.lib(DEFAULT_MODULE).reinitialize()
    return token
