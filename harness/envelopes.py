"""Signed RCAN test envelopes, the keys that sign them and the registry that trusts them.

Shared by the pipeline, auth, audit and envelope tests (the ``receiver`` fixture in
``tests/conftest.py`` trusts :func:`registry`).
"""

from __future__ import annotations

import json
import uuid
from typing import Any

import jwt as pyjwt
from cryptography.hazmat.primitives.asymmetric import ed25519, mldsa
from rcan import RCANMessage
from rcan.signing import MLDSAKeyPair, sign_message

from antireplay.rcan.auth import KeyRegistry, sign_envelope
from antireplay.rcan.receive import Outcome

ED = ed25519.Ed25519PrivateKey.generate()
PQ = mldsa.MLDSA65PrivateKey.generate()
PQ87 = mldsa.MLDSA87PrivateKey.generate()
VIEWER = ed25519.Ed25519PrivateKey.generate()
JWT_KEY = ed25519.Ed25519PrivateKey.generate()
NOW = 1_800_000_000.0
MARKER = "PAYLOAD-MARKER-7f3a"


def registry() -> KeyRegistry:
    keys = KeyRegistry()
    keys.add("op-ed", "operator", "ed25519", ED.public_key(), {"control", "safety"})
    keys.add("op-pq", "operator", "ml-dsa-65", PQ.public_key(), {"control", "safety"})
    keys.add("op-87", "operator", "ml-dsa-87", PQ87.public_key(), {"control"})
    keys.add(
        "op-hy", "operator", "ed25519+ml-dsa-65", (ED.public_key(), PQ.public_key()), {"control"}
    )
    keys.add("viewer", "viewer", "ed25519", VIEWER.public_key(), {"telemetry"})
    return keys


def message(**overrides: Any) -> dict[str, Any]:
    base: dict[str, Any] = {
        "rcan": "3.2",
        "rcan_version": "3.2",
        "msg_id": str(uuid.uuid4()),
        "timestamp": NOW - 1,
        "cmd": "move_forward",
        "target": "rcan://registry.rcan.dev/acme/arm/v2/unit-001",
        "params": {"distance_m": 1.0, "note": MARKER},
    }
    base.update(overrides)
    return base


def signed(kid: str = "op-ed", key: Any = ED, alg: str = "ed25519", **overrides: Any) -> bytes:
    return json.dumps(sign_envelope(message(**overrides), kid, alg, key)).encode()


def token(**claims: Any) -> str:
    body = {"sub": "operator", "exp": NOW + 60, "aud": "robot-1", "iss": "fleet", **claims}
    return pyjwt.encode(body, JWT_KEY, algorithm="EdDSA", headers={"kid": "jwt-1"})


def codes(outcome: Outcome) -> tuple[bool, int, str | None]:
    return outcome.accepted, outcome.status, outcome.code


def sdk_message(**fields: Any) -> tuple[bytes, Any]:
    pair = MLDSAKeyPair.generate()
    msg = RCANMessage(
        cmd="move_forward", target="rcan://registry.rcan.dev/acme/arm/v2/unit-001",
        params={"distance_m": 1.0}, timestamp=NOW - 1, **fields,
    )  # fmt: skip
    sign_message(msg, pair)
    return json.dumps(msg.to_dict()).encode(), pair


def sdk_registry(pair: Any, compat: bool) -> KeyRegistry:
    keys = KeyRegistry(sdk_compat=compat)
    public = mldsa.MLDSA65PublicKey.from_public_bytes(pair.public_key)
    keys.add(pair.key_id, "operator", "ml-dsa-65", public, {"control"})
    return keys


#: Each field a man in the middle may add to a genuine SDK-signed message (but ``qos``,
#: the tolerated delivery hint that is never forwarded).
MITM_FIELDS: dict[str, Any] = {
    "loa": 3, "presence_verified": True, "read_only": True,
    "delegation_chain": [{"issuer": "root", "scope": "*"}], "rcan_version": "3.9",
    "confidence": 0.9, "sender": "admin", "scope": "safety", "sender_type": "human",
    "cloud_provider": "x", "key_id": "other", "sequence_number": 7,
    "group_id": "fleet", "proximity_m": 0.5, "transport_encoding": "cbor",
    "firmware_hash": "ab" * 32, "attestation_ref": "https://x/sbom", "type": 6,
    "safety_event": "ESTOP",
}  # fmt: skip
