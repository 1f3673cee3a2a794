"""Authentication: JWT rules, signature encodings, the key registry's SDK-compat mode and
its key lifecycle (revocation, validity periods, a stale revocation list, reloads)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import jwt as pyjwt
import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec, mldsa
from rcan import RCANMessage
from rcan.signing import MLDSAKeyPair, verify_message

from antireplay import ManualClock, SecurityConfig
from antireplay.audit import AuditLog
from antireplay.cli.demo import write_demo_config
from antireplay.core.errors import KeyRevokedError, SignatureInvalidError
from antireplay.rcan.auth import (
    JwtVerifier,
    KeyRegistry,
    b64decode,
    b64encode,
    load_public_key,
    sdk_key_id,
    sign_envelope,
    sign_sdk,
)
from antireplay.rcan.envelope import parse
from antireplay.rcan.receive import Receiver
from harness import antireplay, fresh_receiver, serving
from harness.envelopes import (
    ED,
    JWT_KEY,
    MARKER,
    NOW,
    PQ,
    codes,
    message,
    registry,
    sdk_message,
    sdk_registry,
    signed,
    token,
)
from harness.stores import aged_state


@pytest.mark.parametrize(
    "claims",
    [
        {"exp": math.nan}, {"exp": math.inf}, {"exp": 10**400}, {"exp": True},
        {"nbf": math.nan}, {"nbf": -math.inf}, {"nbf": -(10**400)}, {"nbf": False},
    ],
    ids=lambda claims: "-".join(f"{k}={v!r}"[:24] for k, v in claims.items()),
)  # fmt: skip
def test_jwt_time_claims_must_be_finite_numbers(
    jwt_receiver: Receiver, claims: dict[str, Any]
) -> None:
    out = jwt_receiver.receive(signed(), {"Authorization": f"Bearer {token(**claims)}"})
    assert (out.code, out.status) == ("AUTH_FAILED", 401)


@pytest.fixture
def jwt_receiver(clock: ManualClock) -> Receiver:
    verifier = JwtVerifier(
        {"jwt-1": JWT_KEY.public_key()}, audience="robot-1", issuer="fleet", clock=clock
    )
    return fresh_receiver(
        SecurityConfig(), registry(), None, None, clock, jwt=verifier, jwt_required=True
    )


@pytest.mark.parametrize(
    ("tok", "code"),
    [
        (token, None),
        (lambda: token(exp=NOW - 1), "AUTH_FAILED"),
        (lambda: token(nbf=NOW + 30), "AUTH_FAILED"),
        (lambda: token(aud="robot-2"), "AUTH_FAILED"),
        (lambda: token(iss="elsewhere"), "AUTH_FAILED"),
        (lambda: token(sub="viewer"), "AUTH_FAILED"),
        (
            lambda: pyjwt.encode({"sub": "operator", "exp": NOW + 60}, "s" * 32, "HS256"),
            "AUTH_FAILED",
        ),
        (lambda: "garbage", "AUTH_FAILED"),
        (lambda: None, "AUTH_FAILED"),
    ],
)
def test_jwt_rules(jwt_receiver: Receiver, tok: Any, code: str | None) -> None:
    value = tok()
    headers = {} if value is None else {"Authorization": f"Bearer {value}"}
    assert jwt_receiver.receive(signed(), headers).code == code


def test_es256_tokens_and_algorithm_confusion(clock: ManualClock) -> None:
    es_key = ec.generate_private_key(ec.SECP256R1())
    verifier = JwtVerifier({"es": es_key.public_key(), "ed": JWT_KEY.public_key()}, clock=clock)
    rx = fresh_receiver(SecurityConfig(), registry(), None, None, clock, jwt=verifier)
    good = pyjwt.encode({"sub": "operator", "exp": NOW + 60}, es_key, "ES256", {"kid": "es"})
    assert rx.receive(signed(), {"Authorization": f"Bearer {good}"}).accepted
    wrong_key = pyjwt.encode({"sub": "operator", "exp": NOW + 60}, es_key, "ES256", {"kid": "ed"})
    assert rx.receive(signed(), {"Authorization": f"Bearer {wrong_key}"}).code == "AUTH_FAILED"


def test_jwt_in_envelope_field(jwt_receiver: Receiver) -> None:
    body = sign_envelope(message(jwt=token()), "op-ed", "ed25519", ED)
    assert jwt_receiver.receive(json.dumps(body).encode()).accepted


def test_sdk_messages_parse_and_verify_only_in_compat_mode(clock: ManualClock) -> None:
    raw, pair = sdk_message()
    strict = fresh_receiver(SecurityConfig(), sdk_registry(pair, False), None, None, clock)
    assert strict.receive(raw).code == "SIGNATURE_INVALID"
    compat = fresh_receiver(SecurityConfig(), sdk_registry(pair, True), None, None, clock)
    out = compat.receive(raw)
    assert out.accepted and out.signer is not None and out.signer.subset
    assert compat.receive(raw).code == "REPLAY_DETECTED"


@pytest.mark.parametrize("value", ["a", "abcde", "\u00e9\u00e9\u00e9\u00e9", "AA=A"])
def test_b64_helper_turns_garbage_into_signature_invalid(receiver: Receiver, value: str) -> None:
    """Our base64url helper: padding optional, garbage a typed SIGNATURE_INVALID (401)."""
    assert b64decode(b64encode(b"\0\xff\xfe")) == b"\0\xff\xfe"  # unpadded, url alphabet
    with pytest.raises(SignatureInvalidError):
        b64decode(value)
    body = json.loads(signed())
    body["sig"]["value"] = value
    assert codes(receiver.receive(json.dumps(body).encode())) == (False, 401, "SIGNATURE_INVALID")


def test_an_unsigned_or_unknown_key_envelope_gets_its_own_code_beside_a_token(
    jwt_receiver: Receiver,
) -> None:
    """One event, one code: a valid bearer token does not turn 'unsigned' or 'unknown key'
    into AUTH_FAILED (which stays the code of a missing or bad token)."""
    unsigned = json.dumps(message()).encode()
    unknown = json.dumps(sign_envelope(message(), "nobody", "ed25519", ED)).encode()
    bearer = {"Authorization": f"Bearer {token()}"}
    assert jwt_receiver.receive(unsigned, bearer).code == "SIGNATURE_REQUIRED"
    assert jwt_receiver.receive(unknown, bearer).code == "UNKNOWN_SENDER"
    assert jwt_receiver.receive(unsigned).code == "AUTH_FAILED"  # the token is required here


def test_public_key_files_pem_or_the_sdk_s_raw_bytes() -> None:
    """One loader: PEM (any supported type) and the SDK's raw ML-DSA keys; the rest by name."""
    pq = mldsa.MLDSA65PrivateKey.generate().public_key()
    pq87 = mldsa.MLDSA87PrivateKey.generate().public_key()
    pem = pq.public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    assert load_public_key(pem) == pq
    assert load_public_key(pq.public_bytes_raw()) == pq
    assert load_public_key(pq87.public_bytes_raw()) == pq87
    with pytest.raises(ValueError, match="1952 or 2592 bytes"):
        load_public_key(b"\x01" * 32)
    with pytest.raises(ValueError, match="SDK private key file"):
        load_public_key(b"MLDS" + b"\x00" * 5990)


def test_sdk_signatures_made_here_verify_with_the_sdk() -> None:
    body = sign_sdk(message(), PQ)
    pair = MLDSAKeyPair.from_public_bytes(PQ.public_key().public_bytes_raw())
    verify_message(RCANMessage.from_dict(body), [pair])
    assert body["sig"]["kid"] == pair.key_id == sdk_key_id(PQ.public_key())
    with pytest.raises(ValueError, match="does not cover scope"):
        sign_sdk(message(scope="safety"), PQ)


def test_an_sdk_key_id_without_sdk_compat_gets_a_hint_naming_it(tmp_path: Path) -> None:
    """A gateway given the SDK's own public key file but not ``sdk_compat: true``: ``config
    check`` warns, and the SDK-signed message's 401 UNKNOWN_SENDER says why in its
    ``detail``; an 8-hex-digit kid of no key is named as SDK-shaped, any other kid gets none."""
    pair = MLDSAKeyPair.generate()
    pair.save(str(tmp_path / "sdk.key"))
    pair.save_public(str(tmp_path / "sdk.pub"))
    entry = {"kid": "sdk-operator", "owner": "operator", "alg": "ml-dsa-65",
             "public_keys": [str(tmp_path / "sdk.pub")], "scopes": ["control"]}  # fmt: skip
    config = write_demo_config(tmp_path, keys=[entry])
    checked = antireplay("config", "check", str(config), cwd=tmp_path)
    assert checked.returncode == 0, checked.stderr
    assert (
        f"antireplay: warning: keys.sdk-operator is an RCAN SDK public key file: the SDK signs "
        f"as its SDK key id {pair.key_id}, which names a key only with sdk_compat: true"
    ) in checked.stderr
    robot = "rcan://registry.rcan.dev/acme/arm/v2/unit-001"
    signed_sdk = antireplay("sign", "--sdk", "--key", "sdk.key", "--cmd", "move_forward",
                            "--target", robot, cwd=tmp_path)  # fmt: skip
    (tmp_path / "sdk.json").write_text(signed_sdk.stdout)
    for kid in ("deadbeef", "nobody"):
        other = antireplay("sign", "--key", "operator.key.pem", "--kid", kid, "--cmd", "c",
                           "--target", robot, cwd=tmp_path)  # fmt: skip
        (tmp_path / f"{kid}.json").write_text(other.stdout)
    aged_state(tmp_path / "state.db")  # history: no first start's fence
    with serving(config) as gateway:
        sent = {n: antireplay("send", "--json", gateway.url, f"{n}.json", cwd=tmp_path)
                for n in ("sdk", "deadbeef", "nobody")}  # fmt: skip
    answers = {name: json.loads(done.stdout) for name, done in sent.items()}
    assert {a["code"] for a in answers.values()} == {"UNKNOWN_SENDER"}
    assert answers["sdk"]["body"]["detail"] == (
        f"sig.kid {pair.key_id} is the RCAN SDK key id of a configured ml-dsa-65 key; "
        "SDK-signed messages verify only with sdk_compat: true"
    )
    assert "shaped like an RCAN SDK key id" in answers["deadbeef"]["body"]["detail"]
    assert "detail" not in answers["nobody"]["body"]


# --- key lifecycle: revocation, validity periods, a stale list, reloads ----------------------


def test_a_revoked_key_is_refused_before_its_signature_and_never_touches_the_seen_set(
    receiver: Receiver, tmp_path: Path
) -> None:
    """Revoked = unauthenticated: 401 KEY_REVOKED with a NACK, no cryptography, audited
    with the code and the kid and no payload; the msg_id is not spent (after unrevoke the
    same message is accepted)."""
    raw = signed()
    receiver.keys.revoked = frozenset({"op-ed"})
    before = receiver.keys.verifications
    out = receiver.receive(raw)
    assert codes(out) == (False, 401, "KEY_REVOKED")
    nack = out.nack
    assert nack is not None and nack["code"] == "KEY_REVOKED"
    assert receiver.keys.verifications == before
    row = AuditLog(tmp_path / "audit.db").tail(1)[0]
    assert (row.code, row.sender, row.warning) == ("KEY_REVOKED", "kid:op-ed", "kid=op-ed")
    assert MARKER not in repr(row)
    receiver.keys.revoked = frozenset()
    assert codes(receiver.receive(raw)) == (True, 200, None)


def test_a_fresh_estop_signed_with_a_revoked_key_is_refused(receiver: Receiver) -> None:
    receiver.keys.revoked = frozenset({"op-ed"})
    out = receiver.receive(signed(type=6, cmd="ESTOP"))
    assert codes(out) == (False, 401, "KEY_REVOKED")


def test_a_key_is_refused_outside_its_validity_period(
    receiver: Receiver, clock: ManualClock
) -> None:
    keys = receiver.keys
    keys.clock = clock
    keys.add("op-new", "operator", "ed25519", ED.public_key(), {"control"},
             not_before=NOW + 10, not_after=NOW + 100)  # fmt: skip
    assert codes(receiver.receive(signed("op-new"))) == (False, 401, "KEY_NOT_YET_VALID")
    clock.step_wall(10)
    assert codes(receiver.receive(signed("op-new", timestamp=NOW + 9))) == (True, 200, None)
    clock.step_wall(90)
    expired = receiver.receive(signed("op-new", timestamp=NOW + 99))
    assert codes(expired) == (False, 401, "KEY_EXPIRED")
    assert expired.error is not None and expired.error.detail == "kid=op-new"


def test_a_stale_revocation_list_passes_only_a_fresh_authentic_estop(
    receiver: Receiver, clock: ManualClock
) -> None:
    """Past ``fresh_until`` the list may miss a revocation: fail closed (503
    STATE_UNAVAILABLE) for all but an ESTOP whose signature verifies."""
    keys = receiver.keys
    keys.freshness = clock
    keys.fresh_until = clock.monotonic() + 1.0
    assert codes(receiver.receive(signed())) == (True, 200, None)
    clock.advance(1.5)
    refused = receiver.receive(signed())
    assert codes(refused) == (False, 503, "STATE_UNAVAILABLE")
    assert refused.error is not None and refused.error.detail == "revocations"
    assert receiver.receive(signed(type=6, cmd="ESTOP")).accepted
    forged = json.loads(signed(type=6, cmd="ESTOP"))
    forged["sig"]["value"] = b64encode(b"\0" * 64)
    bad = receiver.receive(json.dumps(forged).encode())
    assert codes(bad) == (False, 401, "SIGNATURE_INVALID")


def test_replace_swaps_the_whole_key_set_and_keeps_the_revocations() -> None:
    keys, fresh = registry(), KeyRegistry()
    keys.revoked = frozenset({"op-pq"})
    fresh.add("op-new", "operator", "ed25519", ED.public_key())
    keys.replace(fresh)
    assert set(keys.entries) == {"op-new"} and keys.revoked == {"op-pq"}


def test_revoking_a_kid_revokes_its_key_under_every_kid_that_names_it(clock: ManualClock) -> None:
    """The signer picks ``sig.kid``: a second ``keys:`` entry with the same public key, or
    the SDK's 8-hex alias, is refused too, and a reload keeps the key refused."""
    keys = registry()
    keys.add("op-ed-2", "operator", "ed25519", ED.public_key())
    keys.revoked = frozenset({"op-ed"})
    for kid in ("op-ed", "op-ed-2"):
        with pytest.raises(KeyRevokedError):
            keys.verify(parse(signed(kid=kid)))
    fresh = KeyRegistry()
    fresh.add("op-ed-3", "operator", "ed25519", ED.public_key())
    keys.replace(fresh)
    with pytest.raises(KeyRevokedError):
        keys.verify(parse(signed(kid="op-ed-3")))
    alias = KeyRegistry(sdk_compat=True)
    entry = alias.add("op-pq", "operator", "ml-dsa-65", PQ.public_key())
    alias.alias(sdk_key_id(PQ.public_key()), entry)
    alias.revoked = frozenset({sdk_key_id(PQ.public_key())})
    assert alias.refused == {"op-pq", sdk_key_id(PQ.public_key())}
