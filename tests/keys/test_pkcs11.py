"""Keys in a real SoftHSMv2 token: Ed25519 signatures (CKM_EDDSA), HMAC-SHA256
(CKM_SHA256_HMAC) and SHA-256 over a secret key (C_DigestKey) equal what the in-memory key
computes; a MAVLink frame signed through the token is the frame signed with the key; the
DDS fleet key's derived keys are the file psk's; the audit trail's head key in a token; a
token that fails while serving raises TokenUnavailableError (an OSError)."""

from __future__ import annotations

import hashlib
import hmac
from pathlib import Path

import pkcs11
import pytest
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from antireplay.audit import AuditLog, AuditRow, verify
from antireplay.core.errors import StateUnavailableError
from antireplay.epochs.policy import derive_keys
from antireplay.epochs.sealing import topic_key
from antireplay.keys import open_key
from antireplay.keys.pkcs11 import DEFAULT_MODULE, TokenError, TokenUnavailableError
from antireplay.mavlink.codec import parse_frame, sign
from harness.mavlink_frames import unsigned_heartbeat
from harness.softhsm import SoftToken, make_token

KEY = bytes(range(32))


@pytest.fixture
def token(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> SoftToken:
    monkeypatch.setenv("SOFTHSM2_CONF", "")
    return make_token(tmp_path)


class Fixed:
    """The same MAVLink timestamp for both signatures being compared."""

    def next(self) -> int:
        return 1_234_567


def test_an_ed25519_signature_from_the_token_verifies_with_its_public_key(token: SoftToken) -> None:
    public = token.generate_ed25519("operator")
    signer = open_key(token.uri("operator"), "ed25519")
    public.verify(signer.sign(b"an envelope"), b"an envelope")
    assert signer.public_key().public_bytes_raw() == public.public_bytes_raw()


def test_hmac_and_digest_through_the_token_equal_the_in_memory_key(token: SoftToken) -> None:
    token.import_secret("k", KEY)
    assert open_key(token.uri("k"), "hmac").mac(b"data") == hmac.digest(KEY, b"data", "sha256")
    assert (
        open_key(token.uri("k"), "digest").digest(b"data") == hashlib.sha256(KEY + b"data").digest()
    )


def test_a_mavlink_frame_signed_through_the_token_is_the_frame_signed_with_the_key(
    token: SoftToken,
) -> None:
    """SoftHSMv2 digests a sensitive, unextractable secret key (C_DigestKey): the router's
    own signatures can come from the token (the key never in the process)."""
    token.import_secret("mav", KEY)
    frame = parse_frame(unsigned_heartbeat(1))
    through_token = sign(frame, open_key(token.uri("mav"), "digest"), 7, Fixed())
    assert through_token.raw == sign(frame, KEY, 7, Fixed()).raw
    assert through_token.signed and through_token.raw[-6:] == hashlib.sha256(
        KEY + through_token.raw[:-6]).digest()[:6]  # fmt: skip


def test_a_fleet_key_held_as_its_prk_derives_the_file_psks_keys(token: SoftToken) -> None:
    psk = bytes(range(100, 132))
    prk = hmac.digest(bytes(32), psk, "sha256")  # HKDF-Extract with no salt (RFC 5869)
    token.import_secret("fleet", prk)
    fleet = open_key(token.uri("fleet"), "hmac")
    assert derive_keys(fleet) == derive_keys(psk)
    assert topic_key(fleet, "/cmd_vel", "geometry_msgs::msg::Twist", 3) == topic_key(
        psk, "/cmd_vel", "geometry_msgs::msg::Twist", 3)  # fmt: skip
    info = b"antireplay/v1 epoch announcement"
    assert HKDF(hashes.SHA256(), 32, None, info).derive(psk) == fleet.mac(info + b"\x01")


def test_a_token_that_fails_while_serving_raises_an_os_error(token: SoftToken) -> None:
    token.import_secret("k", KEY)
    key = open_key(token.uri("k"), "hmac")
    pkcs11.lib(DEFAULT_MODULE).reinitialize()  # every session of this process is gone
    with pytest.raises(TokenUnavailableError) as caught:
        key.mac(b"data")
    assert isinstance(caught.value, OSError) and token.pin not in str(caught.value)
    assert "SessionHandleInvalid" in str(caught.value)


def test_an_object_of_another_kind_is_not_used(token: SoftToken) -> None:
    token.generate_ed25519("operator")
    with pytest.raises(TokenError, match="no such object: secret key"):
        open_key(token.uri("operator"), "hmac", "audit.head_key")


def row(i: int, outcome: str = "accepted") -> AuditRow:
    return AuditRow(at=1_800_000_000.0 + i, outcome=outcome, msg_type=1, sender="operator",
                    sender_verified=True, msg_id=f"m{i}")  # fmt: skip


def test_the_audit_head_key_in_a_token_macs_the_head_and_segments(
    token: SoftToken, tmp_path: Path
) -> None:
    token.import_secret("audit", KEY)
    log = AuditLog(tmp_path / "audit.db", head_key=open_key(token.uri("audit"), "hmac"))
    for i in range(5):
        log.append(row(i))
    log.close()
    assert not (tmp_path / "audit.db.key").exists()
    report = verify(tmp_path / "audit.db", head_key=open_key(token.uri("audit"), "hmac"))
    assert report.ok and "head checkpoint matches row 5 (MAC verified)" in report.lines()
    # The same MAC as the key in a file would give: the token computed HMAC-SHA256(KEY, head).
    (tmp_path / "audit.db.key").write_text(KEY.hex() + "\n")
    (tmp_path / "audit.db.key").chmod(0o600)
    assert verify(tmp_path / "audit.db").ok


def test_a_token_failing_under_the_writer_refuses_and_the_estop_spill_still_works(
    token: SoftToken, tmp_path: Path
) -> None:
    """The writer's existing failure path: an append it cannot anchor is STATE_UNAVAILABLE
    (callers refuse the message), and an ESTOP row is spilled with the key derived at open;
    the next open, with the token back, merges it into a chain that verifies."""
    token.import_secret("audit", KEY)
    log = AuditLog(tmp_path / "audit.db", head_key=open_key(token.uri("audit"), "hmac"))
    log.append(row(0))
    pkcs11.lib(DEFAULT_MODULE).reinitialize()  # the token goes away while serving
    with pytest.raises(StateUnavailableError, match="audit trail unavailable"):
        log.append(row(1))
    assert log.spill(row(2, "accepted")) and log.spilled == 1
    log.close()
    again = AuditLog(tmp_path / "audit.db", head_key=open_key(token.uri("audit"), "hmac"))
    assert again.spilled == 0
    ids = [r.msg_id for r in again.tail(10)]
    again.close()
    assert "m2" in ids, ids
    assert verify(tmp_path / "audit.db", head_key=open_key(token.uri("audit"), "hmac")).ok


def test_a_secret_that_may_not_sign_is_refused_at_open(token: SoftToken) -> None:
    with token.session() as session:
        session.generate_key(pkcs11.KeyType.GENERIC_SECRET, 256, label="no-sign", store=True,
                             template={pkcs11.Attribute.SIGN: False})  # fmt: skip
    with pytest.raises(TokenError, match=r"may not sign \(CKA_SIGN false\)"):
        open_key(token.uri("no-sign"), "hmac", "audit.head_key")


def test_type_in_the_uri_must_match_the_key_it_opens(token: SoftToken) -> None:
    """``type=`` narrows the object (RFC 7512): a signer named ``type=secret-key`` or
    ``type=public`` is refused, not silently served by the private key."""
    token.generate_ed25519("operator")
    for kind in ("secret-key", "public"):
        uri = token.uri("operator").replace("object=operator", f"object=operator;type={kind}")
        with pytest.raises(TokenError, match=f"type={kind} names no Ed25519 private key"):
            open_key(uri, "ed25519", "--key")
    uri = token.uri("operator").replace("object=operator", "object=operator;type=private")
    open_key(uri, "ed25519", "--key").close()


def test_a_key_of_another_type_says_wrong_key_type(token: SoftToken) -> None:
    """An HMAC secret or a P-256 key where an Ed25519 key is needed: its type, one line."""
    token.import_secret("mac", KEY)
    with token.session() as session:
        session.generate_keypair(
            pkcs11.KeyType.EC, store=True, label="p256", id=b"p256",
            mechanism=pkcs11.Mechanism.EC_KEY_PAIR_GEN,
            public_template={pkcs11.Attribute.EC_PARAMS: bytes.fromhex("06082a8648ce3d030107")},
        )  # fmt: skip
    with pytest.raises(TokenError, match="wrong key type: the object is a generic_secret secret"):
        open_key(token.uri("mac"), "ed25519", "--key")
    with pytest.raises(TokenError, match="wrong key type: the object is a ec private_key"):
        open_key(token.uri("p256"), "ed25519", "--key")
