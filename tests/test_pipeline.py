"""The receive pipeline: §8.3 order, check -> authenticate -> commit, NACKs, audit."""

from __future__ import annotations

import json
import math
import sqlite3
import uuid
from pathlib import Path
from typing import Any

import jwt as pyjwt
import pytest
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, mldsa
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rcan import RCANMessage
from rcan.signing import MLDSAKeyPair, _canonical_message_bytes, sign_message

from antireplay import ManualClock, SecurityConfig
from antireplay.audit import AuditLog, verify
from antireplay.auth import JwtVerifier, KeyRegistry, b64decode, b64encode, sign_envelope
from antireplay.envelope import SDK_SIGNED_FIELDS, encode
from antireplay.errors import SignatureInvalidError
from antireplay.pipeline import Outcome, Receiver
from tests.conftest import fresh_receiver, race

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


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(wall=NOW)


@pytest.fixture
def receiver(tmp_path: Path, clock: ManualClock) -> Receiver:
    return fresh_receiver(
        SecurityConfig(), registry(), None, AuditLog(tmp_path / "audit.db"), clock
    )


def codes(outcome: Outcome) -> tuple[bool, int, str | None]:
    return outcome.accepted, outcome.status, outcome.code


# --- acceptance and the basic answers ------------------------------------------------------------


@pytest.mark.parametrize(
    ("kid", "key", "alg"),
    [
        ("op-ed", ED, "ed25519"),
        ("op-pq", PQ, "ml-dsa-65"),
        ("op-87", PQ87, "ml-dsa-87"),
        ("op-hy", (ED, PQ), "ed25519+ml-dsa-65"),
    ],
)
def test_fresh_signed_message_accepted(receiver: Receiver, kid: str, key: Any, alg: str) -> None:
    out = receiver.receive(signed(kid, key, alg))
    assert codes(out) == (True, 200, None)
    assert out.signer is not None and out.signer.owner == "operator"


def test_exact_replay_is_409_with_nack(receiver: Receiver) -> None:
    raw = signed()
    assert receiver.receive(raw).accepted
    out = receiver.receive(raw)
    assert codes(out) == (False, 409, "REPLAY_DETECTED")
    assert out.nack is not None
    assert out.nack["type"] == 18 and out.nack["code"] == "REPLAY_DETECTED"
    assert out.nack["ref_msg_id"] == json.loads(raw)["msg_id"]


def test_legacy_nack_type_31(tmp_path: Path, clock: ManualClock) -> None:
    rx = fresh_receiver(SecurityConfig(nack_type=31), registry(), None, None, clock)
    raw = signed()
    rx.receive(raw)
    nack = rx.receive(raw).nack
    assert nack is not None and nack["type"] == 31


def test_stale_is_408(receiver: Receiver) -> None:
    assert codes(receiver.receive(signed(timestamp=NOW - 31))) == (False, 408, "MESSAGE_STALE")


def test_timestamp_ms_accepted_and_exact(receiver: Receiver) -> None:
    raw = signed(timestamp=None, timestamp_ms=int((NOW - 2) * 1000))
    body = json.loads(raw)
    body.pop("timestamp")
    body = sign_envelope({k: v for k, v in body.items() if k != "sig"}, "op-ed", "ed25519", ED)
    assert receiver.receive(json.dumps(body).encode()).accepted


# --- every step's rejection, in order -------------------------------------------------------------


def test_steps_reject_in_order(receiver: Receiver) -> None:
    huge = json.dumps(message(params={"blob": "x" * 70_000})).encode()
    deep: dict[str, Any] = {}
    for _ in range(30):
        deep = {"d": deep}
    cases = [
        (b"not json", "INVALID_ENVELOPE"),
        (b"[1,2,3]", "INVALID_ENVELOPE"),
        (huge, "INVALID_ENVELOPE"),
        (json.dumps(message(params=deep)).encode(), "INVALID_ENVELOPE"),
        (json.dumps({**message(), "surprise": 1}).encode(), "INVALID_ENVELOPE"),
        (signed(rcan="2.0", rcan_version="2.0"), "VERSION_INCOMPATIBLE"),
        (signed(msg_id=""), "INVALID_MESSAGE_ID"),
        (signed(timestamp="nan"), "INVALID_TIMESTAMP"),
        (signed(timestamp=NOW + 60), "MESSAGE_FROM_FUTURE"),
        (json.dumps(message()).encode(), "SIGNATURE_REQUIRED"),
        (signed("viewer", VIEWER), "SCOPE_DENIED"),
    ]
    for raw, code in cases:
        out = receiver.receive(raw)
        assert (out.accepted, out.code) == (False, code), (code, out.reason)
        assert 400 <= out.status < 500


def test_stale_and_badly_signed_reports_stale(receiver: Receiver) -> None:
    bad = json.loads(signed(timestamp=NOW - 100))
    bad["sig"]["value"] = "AAAA"
    assert receiver.receive(json.dumps(bad).encode()).code == "MESSAGE_STALE"


def test_bad_version_and_stale_reports_version(receiver: Receiver) -> None:
    raw = signed(timestamp=NOW - 100, rcan="9.0", rcan_version="9.0")
    out = receiver.receive(raw)
    assert (out.code, out.status) == ("VERSION_INCOMPATIBLE", 426)


def test_replay_and_stale_paths_do_no_crypto(tmp_path: Path, clock: ManualClock) -> None:
    keys = registry()
    jwt_verifier = JwtVerifier({"jwt-1": JWT_KEY.public_key()}, clock=clock)
    rx = fresh_receiver(SecurityConfig(), keys, None, None, clock, jwt=jwt_verifier)
    raw = signed()
    rx.receive(raw, {"Authorization": f"Bearer {token()}"})
    before = (keys.verifications, jwt_verifier.decodes)
    for _ in range(50):
        assert rx.receive(raw, {"Authorization": f"Bearer {token()}"}).code == "REPLAY_DETECTED"
        stale = signed(timestamp=NOW - 100)
        assert rx.receive(stale, {"Authorization": f"Bearer {token()}"}).code == "MESSAGE_STALE"
    assert (keys.verifications, jwt_verifier.decodes) == before


# --- cache poisoning and signature coverage -------------------------------------------------------


def test_forged_message_cannot_poison_the_cache(receiver: Receiver) -> None:
    genuine = json.loads(signed())
    forged = {**genuine, "cmd": "self_destruct"}
    assert codes(receiver.receive(json.dumps(forged).encode()))[2] == "SIGNATURE_INVALID"
    assert receiver.receive(json.dumps(genuine).encode()).accepted


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("qos", 2),
        ("scope", "admin"),
        ("type", 6),
        ("safety_event", "ESTOP"),
        ("target", "rcan://other"),
        ("timestamp", NOW - 2),
        ("sender", "someone-else"),
        ("params", {"distance_m": 100.0}),
    ],
)
def test_policy_fields_are_covered_by_the_signature(
    receiver: Receiver, field: str, value: Any
) -> None:
    body = json.loads(signed())
    body[field] = value
    assert receiver.receive(json.dumps(body).encode()).code == "SIGNATURE_INVALID"


# --- ESTOP end to end ----------------------------------------------------------------------------


def test_estop_invariant_end_to_end(tmp_path: Path, receiver: Receiver) -> None:
    estop = signed(type=6, safety_event="ESTOP", cmd="estop")
    assert codes(receiver.receive(estop)) == (True, 200, None)
    again = receiver.receive(estop)
    assert again.accepted and again.warning == "REPLAY_DETECTED"
    stale = signed(type=6, safety_event="ESTOP", cmd="estop", timestamp=NOW - 11)
    assert receiver.receive(stale).code == "MESSAGE_STALE"
    resume = signed(type=6, safety_event="RESUME", cmd="resume")
    assert receiver.receive(resume).accepted
    assert receiver.receive(resume).code == "REPLAY_DETECTED"
    assert receiver.audit is not None
    warned = [r for r in receiver.audit.tail(50) if r.warning == "REPLAY_DETECTED"]
    assert len(warned) == 1 and warned[0].outcome == "accepted"


def test_safety_needs_the_safety_scope(receiver: Receiver) -> None:
    out = receiver.receive(signed("op-87", PQ87, "ml-dsa-87", type=6, safety_event="ESTOP"))
    assert out.code == "SCOPE_DENIED" and out.status == 403


# --- races --------------------------------------------------------------------------------------


def test_copies_racing_through_crypto_one_wins(receiver: Receiver) -> None:
    for _ in range(20):
        raw = signed("op-pq", PQ, "ml-dsa-65")
        outcomes: list[Outcome] = []

        def deliver(r: bytes = raw, out: list[Outcome] = outcomes) -> None:
            out.append(receiver.receive(r))

        race(6, deliver)
        assert sorted(o.code or "OK" for o in outcomes) == ["OK"] + ["REPLAY_DETECTED"] * 5


# --- JWT --------------------------------------------------------------------------------------


def token(**claims: Any) -> str:
    body = {"sub": "operator", "exp": NOW + 60, "aud": "robot-1", "iss": "fleet", **claims}
    return pyjwt.encode(body, JWT_KEY, algorithm="EdDSA", headers={"kid": "jwt-1"})


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


# --- the official RCAN SDK --------------------------------------------------------------------


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


def test_sdk_messages_parse_and_verify_only_in_compat_mode(clock: ManualClock) -> None:
    raw, pair = sdk_message()
    strict = fresh_receiver(SecurityConfig(), sdk_registry(pair, False), None, None, clock)
    assert strict.receive(raw).code == "SIGNATURE_INVALID"
    compat = fresh_receiver(SecurityConfig(), sdk_registry(pair, True), None, None, clock)
    out = compat.receive(raw)
    assert out.accepted and out.signer is not None and out.signer.subset
    assert compat.receive(raw).code == "REPLAY_DETECTED"


@pytest.mark.parametrize("field", [{"qos": 1}, {"scope": "control"}])
def test_compat_mode_refuses_unsigned_policy_fields(clock: ManualClock, field: Any) -> None:
    raw, pair = sdk_message(**field)
    compat = fresh_receiver(SecurityConfig(), sdk_registry(pair, True), None, None, clock)
    assert compat.receive(raw).code == "SCOPE_DENIED"


def test_sdk_signed_fields_are_what_the_sdk_signs() -> None:
    """Ask the installed SDK which attributes its canonical bytes read: exactly ours."""
    probe = RCANMessage(cmd="c", target="rcan://registry.rcan.dev/acme/arm/v2/unit-001")
    covered = set(json.loads(_canonical_message_bytes(probe)))
    assert covered == SDK_SIGNED_FIELDS
    # Changing any other field leaves the SDK's signed bytes unchanged: they are unsigned.
    before = _canonical_message_bytes(probe)
    for name, value in MITM_FIELDS.items():
        setattr(probe, name, value)
    assert _canonical_message_bytes(probe) == before


#: Each field a man in the middle may add to a genuine SDK-signed message.
MITM_FIELDS: dict[str, Any] = {
    "loa": 3, "presence_verified": True, "read_only": True,
    "delegation_chain": [{"issuer": "root", "scope": "*"}], "rcan_version": "3.9",
    "confidence": 0.9, "sender": "admin", "scope": "safety", "sender_type": "human",
    "cloud_provider": "x", "key_id": "other", "qos": 2, "sequence_number": 7,
    "group_id": "fleet", "proximity_m": 0.5, "transport_encoding": "cbor",
    "firmware_hash": "ab" * 32, "attestation_ref": "https://x/sbom", "type": 6,
    "safety_event": "ESTOP",
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(MITM_FIELDS))
def test_compat_mode_refuses_every_field_the_sdk_does_not_sign(
    clock: ManualClock, name: str
) -> None:
    raw, pair = sdk_message()
    compat = fresh_receiver(SecurityConfig(), sdk_registry(pair, True), None, None, clock)
    body = {**json.loads(raw), name: MITM_FIELDS[name]}
    out = compat.receive(json.dumps(body).encode())
    assert (out.code, out.status) == ("SCOPE_DENIED", 403)
    assert name in (out.reason or "")
    assert compat.receive(raw).accepted  # the genuine message was not spent by the forgery


def test_compat_mode_forwards_exactly_the_signed_fields(clock: ManualClock) -> None:
    raw, pair = sdk_message()
    compat = fresh_receiver(SecurityConfig(), sdk_registry(pair, True), None, None, clock)
    out = compat.receive(raw)
    assert out.accepted and out.envelope is not None
    forwarded = json.loads(encode(out.envelope))
    assert set(forwarded) == {*SDK_SIGNED_FIELDS, "rcan_version", "sig"}
    assert forwarded["rcan_version"] == forwarded["rcan"]


def test_compat_mode_tampered_unsigned_field_is_refused(clock: ManualClock) -> None:
    raw, pair = sdk_message()
    body = json.loads(raw)
    body["type"], body["safety_event"] = 6, "ESTOP"  # not covered by the SDK signature
    compat = fresh_receiver(SecurityConfig(), sdk_registry(pair, True), None, None, clock)
    assert compat.receive(json.dumps(body).encode()).code == "SCOPE_DENIED"


# --- audit trail -------------------------------------------------------------------------------


def test_audit_chain_verifies_and_tamper_is_found(tmp_path: Path, receiver: Receiver) -> None:
    raw = signed()
    receiver.receive(raw)
    receiver.receive(raw)
    receiver.receive(signed(timestamp=NOW - 100))
    receiver.receive(signed())
    path = tmp_path / "audit.db"
    report = verify(path)
    assert report.ok and report.records == 4
    db = sqlite3.connect(path)
    db.execute("UPDATE audit SET code = 'OK' WHERE seq = 2")
    db.commit()
    db.close()
    report = verify(path)
    assert (report.ok, report.broken_at) == (False, 2)


def test_audit_deleted_record_is_found(tmp_path: Path, receiver: Receiver) -> None:
    for _ in range(3):
        receiver.receive(signed())
    db = sqlite3.connect(tmp_path / "audit.db")
    db.execute("DELETE FROM audit WHERE seq = 2")
    db.commit()
    db.close()
    assert verify(tmp_path / "audit.db").broken_at == 2


def test_no_payload_ever_reaches_the_audit_database(tmp_path: Path, receiver: Receiver) -> None:
    hostile_id = f"id\n2026-01-01 ACCEPTED admin {MARKER}"
    raw = signed(msg_id=hostile_id[:100])
    receiver.receive(raw)
    receiver.receive(raw)
    forged = {**message(), "sig": {"alg": "x", "kid": "k", "value": "y"}}
    receiver.receive(json.dumps(forged).encode())
    receiver.receive(signed(timestamp=NOW - 99, sender="claimed-bob"))
    assert receiver.audit is not None
    receiver.audit.close()
    blob = b"".join(p.read_bytes() for p in tmp_path.iterdir() if p.name.startswith("audit.db"))
    assert MARKER.encode() not in blob
    assert b"\n2026-01-01" not in blob
    records = AuditLog(tmp_path / "audit.db").tail()
    assert all("\n" not in (r.msg_id or "") for r in records)
    assert [r.sender_verified for r in records if r.sender == "claimed-bob"] == [False]


def test_garbage_flood_audit_is_rate_limited(tmp_path: Path, receiver: Receiver) -> None:
    for _ in range(100):
        receiver.receive(b"{")
    assert receiver.audit is not None
    assert receiver.audit.count() <= 11
    assert receiver.stats.rejected["INVALID_ENVELOPE"] == 100
    assert receiver.stats.unaudited >= 89


# --- fuzzing ----------------------------------------------------------------------------------

JSONISH = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda kids: (
        st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=8), kids, max_size=4)
    ),
    max_leaves=12,
)
FIELDS = st.sampled_from(
    ["msg_id", "timestamp", "timestamp_ms", "cmd", "target", "rcan", "rcan_version", "type",
     "safety_event", "params", "sig", "scope", "qos", "sender", "jwt", "extra"]
)  # fmt: skip
FUZZ_RX = fresh_receiver(SecurityConfig(), registry(), None, None, ManualClock(wall=NOW))


def _check_outcome(out: Outcome) -> None:
    assert isinstance(out, Outcome)
    if not out.accepted:
        assert 400 <= out.status < 500 and out.code


@settings(max_examples=6_000, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.binary(max_size=300))
def test_fuzz_bytes_only_typed_rejections(raw: bytes) -> None:
    _check_outcome(FUZZ_RX.receive(raw))


@settings(max_examples=6_000, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.dictionaries(FIELDS, JSONISH, max_size=10), st.booleans())
def test_fuzz_envelopes_only_typed_rejections(body: dict[str, Any], base: bool) -> None:
    doc = {**message(), **body} if base else body
    try:
        raw = json.dumps(doc).encode()
    except ValueError:
        return
    _check_outcome(FUZZ_RX.receive(raw))


@pytest.mark.parametrize("value", ["a", "abcde", "\u00e9\u00e9\u00e9\u00e9", "AA=A"])
def test_b64_helper_turns_garbage_into_signature_invalid(receiver: Receiver, value: str) -> None:
    """Our base64url helper: padding optional, garbage a typed SIGNATURE_INVALID (401)."""
    assert b64decode(b64encode(b"\0\xff\xfe")) == b"\0\xff\xfe"  # unpadded, url alphabet
    with pytest.raises(SignatureInvalidError):
        b64decode(value)
    body = json.loads(signed())
    body["sig"]["value"] = value
    assert codes(receiver.receive(json.dumps(body).encode())) == (False, 401, "SIGNATURE_INVALID")


def test_exact_copy_memo_and_its_limits(receiver: Receiver, clock: ManualClock) -> None:
    raw = signed()
    assert receiver.receive(raw).accepted
    assert receiver.receive(raw).code == "REPLAY_DETECTED"  # byte-identical: caught before parsing
    reserialized = json.dumps(json.loads(raw), indent=1).encode()
    assert receiver.receive(reserialized).code == "REPLAY_DETECTED"  # same message, other bytes
    clock.advance(31)
    assert receiver.receive(raw).code == "MESSAGE_STALE"  # the memo never outlives the window
    assert receiver.audit is not None
    codes_seen = [r.code for r in receiver.audit.tail(10)]
    assert codes_seen == [None, "REPLAY_DETECTED", "REPLAY_DETECTED", "MESSAGE_STALE"]


def test_rejected_messages_never_enter_the_copy_memo(receiver: Receiver) -> None:
    body = json.loads(signed())
    forged = json.dumps({**body, "cmd": "arm"}).encode()
    assert receiver.receive(forged).code == "SIGNATURE_INVALID"
    assert receiver.receive(forged).code == "SIGNATURE_INVALID"  # not REPLAY: never accepted


def test_unauditable_accept_is_refused_not_lost(tmp_path: Path, receiver: Receiver) -> None:
    assert receiver.audit is not None
    receiver.audit.close()  # the audit database is gone (disk full, unmounted…)
    out = receiver.receive(signed())
    assert (out.accepted, out.status, out.code) == (False, 503, "STATE_UNAVAILABLE")
    assert receiver.stats.accepted == 0
    assert receiver.stats.audit_failures == 2  # the accept, then its 503 answer
    assert receiver.receive(signed(timestamp=NOW - 100)).code == "MESSAGE_STALE"
