"""Authentication: envelope signatures (Ed25519, ML-DSA-65/87, hybrid), JWTs, the key registry.

Theory of operation
-------------------
A :class:`KeyRegistry` maps a ``kid`` to a :class:`KeyEntry`: the owner (the
identity a JWT subject must match), the algorithm, the public key(s) and the
scopes the owner may use.  ``verify`` checks ``sig`` over
:func:`~antireplay.rcan.envelope.canonical_bytes` (every field but ``sig``/``jwt``).
Algorithms (``sig.alg``):

* ``ed25519``, ``ml-dsa-65``, ``ml-dsa-87``: one signature, via ``cryptography``;
* ``ed25519+ml-dsa-65``: hybrid, ``value`` is ``<ed25519>.<ml-dsa-65>`` and both
  must verify (secure while either algorithm stands).

Compatibility mode (off by default): a ``ml-dsa-65`` signature made by the
official RCAN SDK covers only ``rcan, msg_id, timestamp, cmd, target, params``.
With ``sdk_compat=True`` such a signature is accepted, but the result is
marked ``subset=True`` and the pipeline refuses the message if it sets any
field the SDK does not sign (everything but ``rcan, msg_id, timestamp, cmd,
target, params``; see :func:`~antireplay.rcan.envelope.unsigned_policy_fields`), so
nothing unsigned is authorized or forwarded (the SDK's ``qos`` delivery hint is
tolerated and dropped).  The SDK signs with ``sig.kid`` = its key id
(:func:`sdk_key_id`: SHA-256 of the raw public key, 8 hex digits); a registry
can answer to it as well (:meth:`KeyRegistry.alias`, done by
:func:`~antireplay.wiring.build_registry` in compatibility mode), and
:func:`sign_sdk` signs the way the SDK's ``sign_message`` does.

Key lifecycle, checked in :meth:`KeyRegistry.signing_key` before any cryptography (a set
lookup and two comparisons, no store round trip): a kid in ``revoked`` (the shared
revocation list, kept fresh by the gateway's watcher, :mod:`antireplay.wiring.keys`) is
``KEY_REVOKED``; outside its ``not_before`` / ``not_after`` a key is ``KEY_NOT_YET_VALID`` /
``KEY_EXPIRED``.  Past ``fresh_until`` (the watcher's last good refresh plus its 1 s
promise, on the watcher's monotonic clock, ``freshness``) the list may be stale: every
message but an ESTOP is ``STATE_UNAVAILABLE``; an ESTOP from a key not known revoked still
needs its signature.
:meth:`KeyRegistry.replace` swaps in a reloaded key set in one assignment.

Key files: :func:`load_public_key` is the one loader (``config check``,
``serve``, the library): PEM, or the SDK's raw ML-DSA public key file.

Every call that does cryptography increments ``verifications`` (and
:class:`JwtVerifier` ``decodes``), so tests can prove that a replay or a stale
message was thrown away before any of it.

JWTs (PyJWT): from ``Authorization: Bearer`` or the envelope's ``jwt`` field;
EdDSA and ES256 always, HS256 only when a shared secret is configured.
``exp`` and ``nbf`` are enforced with the receiver's :class:`Clock` (not the
library's) and must be finite numbers (``NaN``, ``Infinity``, ``true`` or an
integer beyond a float's range is ``AUTH_FAILED``), ``aud`` and ``iss`` by
PyJWT; ``sub`` must equal the signing key's owner.

Size: one idea, who may sign: the key registry with its validity periods and revocations,
and the verification it answers; apart, each half would re-derive the other's rule.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import jwt
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, mldsa

from antireplay.core.clock import Clock, SystemClock, resolve
from antireplay.core.errors import (
    AuthFailedError,
    KeyExpiredError,
    KeyNotYetValidError,
    KeyRevokedError,
    SignatureInvalidError,
    SignatureRequiredError,
    StateUnavailableError,
    UnknownSenderError,
)
from antireplay.core.messages import MessageType, SafetyEvent
from antireplay.rcan.envelope import (
    Envelope,
    Signature,
    canonical_bytes,
    parse,
    safety_class,
    sdk_signed_bytes,
    unsigned_policy_fields,
)

PublicKey = ed25519.Ed25519PublicKey | mldsa.MLDSA65PublicKey | mldsa.MLDSA87PublicKey
ALGORITHMS: dict[str, tuple[type, ...]] = {
    "ed25519": (ed25519.Ed25519PublicKey,),
    "ml-dsa-65": (mldsa.MLDSA65PublicKey,),
    "ml-dsa-87": (mldsa.MLDSA87PublicKey,),
    "ed25519+ml-dsa-65": (ed25519.Ed25519PublicKey, mldsa.MLDSA65PublicKey),
}


@dataclass(frozen=True)
class KeyEntry:
    """One signing key: who owns it, how it signs, what it may do."""

    kid: str
    owner: str
    alg: str
    public_keys: tuple[PublicKey, ...]
    scopes: frozenset[str] = frozenset({"control"})
    not_before: float | None = None  # Unix seconds; None: unbounded
    not_after: float | None = None


_ESTOP = (int(MessageType.SAFETY), str(SafetyEvent.ESTOP))
_SYSTEM_CLOCK = SystemClock()  # one, not one per request (the freshness check)


@dataclass(frozen=True)
class Signer:
    """The authenticated origin of a message."""

    kid: str
    owner: str
    scopes: frozenset[str]
    subset: bool = False  # True: only the SDK's field subset is signed


def b64decode(value: str) -> bytes:
    """base64url with or without padding; typed error on garbage."""
    try:
        return base64.urlsafe_b64decode(value + "=" * (-len(value) % 4))
    except (binascii.Error, ValueError):
        raise SignatureInvalidError("signature is not base64url") from None


def b64encode(raw: bytes) -> str:
    return base64.urlsafe_b64encode(raw).rstrip(b"=").decode()


#: Raw FIPS 204 public keys by length: what the RCAN SDK's ``MLDSAKeyPair.save_public`` writes.
RAW_PUBLIC_KEYS: dict[int, type[mldsa.MLDSA65PublicKey] | type[mldsa.MLDSA87PublicKey]] = {
    1952: mldsa.MLDSA65PublicKey,
    2592: mldsa.MLDSA87PublicKey,
}
#: The first bytes of the RCAN SDK's private key file (``MLDSAKeyPair.save``).
SDK_PRIVATE_MAGIC = b"MLDS"


def load_public_key(data: bytes) -> PublicKey:
    """A public key file as written by ``antireplay keygen`` (PEM) or the RCAN SDK (raw).

    The one loader for ``config check``, ``serve`` and the library: PEM
    SubjectPublicKeyInfo, or a raw ML-DSA-65/87 public key (the SDK's
    ``MLDSAKeyPair.save_public``, 1,952 bytes).  The SDK writes no Ed25519 key files
    (``rcan.signing.KeyPair`` is deprecated).  The SDK's private key file is refused
    by name: a receiver needs, and should hold, only the public half.
    """
    if data.startswith(b"-----BEGIN"):
        key = serialization.load_pem_public_key(data)
        if not isinstance(
            key, ed25519.Ed25519PublicKey | mldsa.MLDSA65PublicKey | mldsa.MLDSA87PublicKey
        ):
            raise ValueError(f"unsupported public key type {type(key).__name__}")
        return key
    if data.startswith(SDK_PRIVATE_MAGIC):
        raise ValueError(
            "this is an RCAN SDK private key file (MLDSAKeyPair.save); give the receiver "
            "the public key file (MLDSAKeyPair.save_public)"
        )
    kind = RAW_PUBLIC_KEYS.get(len(data))
    if kind is None:
        raise ValueError(
            f"not a PEM public key nor a raw ML-DSA-65/87 public key ({len(data)} bytes; "
            f"raw keys are {' or '.join(map(str, RAW_PUBLIC_KEYS))} bytes)"
        )
    return kind.from_public_bytes(data)


#: What an RCAN SDK key id looks like (:func:`sdk_key_id`).
_SDK_KID = re.compile(r"[0-9a-f]{8}")


def sdk_key_id(key: PublicKey) -> str:
    """The RCAN SDK's key id: the first 8 hex digits of SHA-256 over the raw public key
    (``MLDSAKeyPair.key_id``); the SDK's ``sign_message`` puts it in ``sig.kid``."""
    return hashlib.sha256(key.public_bytes_raw()).hexdigest()[:8]


def _check(key: PublicKey, sig: bytes, data: bytes) -> bool:
    try:
        key.verify(sig, data)
    except InvalidSignature:
        return False
    return True


@dataclass
class KeyRegistry:
    """kid -> :class:`KeyEntry`; verifies envelope signatures."""

    entries: dict[str, KeyEntry] = field(default_factory=dict)
    sdk_compat: bool = False
    verifications: int = 0
    clock: Clock | None = None
    #: Revoked kids (the shared list, replaced whole by the watcher).
    revoked: frozenset[str] = frozenset()
    #: Monotonic time until which ``revoked`` is known fresh (then: refuse all but an ESTOP),
    #: on ``freshness`` (the watcher's clock: real time; ``None``: the system clock).
    fresh_until: float = math.inf
    freshness: Clock | None = None
    #: Every kid refused: the revoked kids and every kid naming one of their public keys
    #: (a second ``keys:`` entry, the SDK alias); derived whenever ``revoked`` or ``entries``
    #: is assigned, so the request path stays one set lookup.
    refused: frozenset[str] = field(default=frozenset(), init=False, compare=False)

    def __setattr__(self, name: str, value: object) -> None:
        object.__setattr__(self, name, value)
        if name in ("revoked", "entries"):
            self._derive_refused()

    def _derive_refused(self) -> None:
        """Revocation is of the key, not of the kid string (the signer picks ``sig.kid``);
        a kid's keys are remembered after a reload drops it, so renaming does not un-revoke."""
        revoked: frozenset[str] = getattr(self, "revoked", frozenset())
        entries: dict[str, KeyEntry] = getattr(self, "entries", {})
        known: dict[str, frozenset[bytes]] = self.__dict__.setdefault("_known", {})
        for kid, entry in entries.items():
            known[kid] = known.get(kid, frozenset()) | {
                k.public_bytes_raw() for k in entry.public_keys
            }
        keys = frozenset().union(*(known.get(kid, frozenset()) for kid in revoked))
        named = {
            kid
            for kid, entry in entries.items()
            if any(key.public_bytes_raw() in keys for key in entry.public_keys)
        }
        object.__setattr__(self, "refused", frozenset(revoked | named))

    def add(
        self,
        kid: str,
        owner: str,
        alg: str,
        public_keys: PublicKey | tuple[PublicKey, ...],
        scopes: frozenset[str] | set[str] = frozenset({"control"}),
        *,
        not_before: float | None = None,
        not_after: float | None = None,
    ) -> KeyEntry:
        keys = public_keys if isinstance(public_keys, tuple) else (public_keys,)
        expected = ALGORITHMS.get(alg)
        if expected is None or len(keys) != len(expected):
            raise ValueError(f"unsupported algorithm {alg!r} for {len(keys)} key(s)")
        for key, kind in zip(keys, expected, strict=True):
            if not isinstance(key, kind):
                raise ValueError(f"{alg} needs a {kind.__name__}, got {type(key).__name__}")
        if kid in self.entries:  # two keys under one kid: which one signed would be unknowable
            raise ValueError(f"kid {kid!r} is already registered")
        entry = KeyEntry(kid, owner, alg, keys, frozenset(scopes), not_before, not_after)
        self.entries[kid] = entry
        self._derive_refused()
        return entry

    def alias(self, kid: str, entry: KeyEntry) -> None:
        """Let ``entry`` answer to a second kid as well (the RCAN SDK's key id, which the
        SDK always puts in ``sig.kid``); never shadows another key."""
        other = self.entries.get(kid)
        if other is not None and other != entry:
            raise ValueError(f"kid {kid!r} (the SDK key id of {entry.kid!r}) names another key")
        self.entries[kid] = entry
        self._derive_refused()

    def signing_key(self, env: Envelope) -> tuple[Signature, KeyEntry]:
        """The signature block and the registered key it names (no cryptography); raises
        ``SIGNATURE_REQUIRED`` (unsigned) or ``UNKNOWN_SENDER`` (key id not registered)."""
        sig = env.signature()
        if sig is None:
            raise SignatureRequiredError("message is not signed")
        entry = self.entries.get(sig.kid)
        if entry is None:
            raise UnknownSenderError("unknown signing key", detail=self._sdk_hint(sig.kid))
        if self.refused and (entry.kid in self.refused or sig.kid in self.refused):
            raise KeyRevokedError("signing key is revoked", detail=f"kid={entry.kid}")
        if entry.not_before is not None or entry.not_after is not None:
            self._check_period(entry)
        if self.fresh_until < math.inf and self.stale() and safety_class(env) != _ESTOP:
            raise StateUnavailableError(
                "revocation list not refreshed in time; only a fresh ESTOP passes",
                detail="revocations",
            )
        return sig, entry

    def stale(self) -> bool:
        """Whether the revocation list is past its promise (the watcher has not refreshed it)."""
        clock = self.freshness if self.freshness is not None else _SYSTEM_CLOCK
        return clock.monotonic() > self.fresh_until

    def _check_period(self, entry: KeyEntry) -> None:
        now = resolve(self.clock).wall()
        if entry.not_before is not None and now < entry.not_before:
            raise KeyNotYetValidError("signing key is not valid yet", detail=f"kid={entry.kid}")
        if entry.not_after is not None and now >= entry.not_after:
            raise KeyExpiredError("signing key has expired", detail=f"kid={entry.kid}")

    def replace(self, other: KeyRegistry) -> None:
        """Take ``other``'s keys in one assignment (a reload: a request sees the old set or
        the new one, never a mix); the revocation state stays."""
        self.entries = other.entries

    def _sdk_hint(self, kid: str) -> str | None:
        """Why an unknown kid may be an RCAN SDK key id (the SDK always signs with it, and
        it names a key only with ``sdk_compat``); ``None`` if nothing suggests it."""
        if self.sdk_compat or not _SDK_KID.fullmatch(kid):
            return None
        ours = any(
            entry.alg == "ml-dsa-65" and sdk_key_id(entry.public_keys[0]) == kid
            for entry in self.entries.values()
        )
        whose = (
            "the RCAN SDK key id of a configured ml-dsa-65 key"
            if ours
            else ("shaped like an RCAN SDK key id (8 hex digits)")
        )
        return f"sig.kid {kid} is {whose}; SDK-signed messages verify only with sdk_compat: true"

    def verify(self, env: Envelope) -> Signer:
        """Verify ``env.sig``; raises ``SIGNATURE_REQUIRED``, ``UNKNOWN_SENDER``,
        ``KEY_REVOKED``, ``KEY_EXPIRED``, ``KEY_NOT_YET_VALID`` or ``SIGNATURE_INVALID``
        (all 401), or ``STATE_UNAVAILABLE`` (503) while the revocation list is stale."""
        sig, entry = self.signing_key(env)
        if sig.alg != entry.alg:
            raise SignatureInvalidError("signature algorithm does not match the key")
        parts = sig.value.split(".")
        if len(parts) != len(entry.public_keys):
            raise SignatureInvalidError("wrong number of signature parts")
        raw = [b64decode(p) for p in parts]
        self.verifications += 1
        data = canonical_bytes(env)
        if all(_check(k, s, data) for k, s in zip(entry.public_keys, raw, strict=True)):
            return Signer(entry.kid, entry.owner, entry.scopes)
        if self.sdk_compat and entry.alg == "ml-dsa-65" and env.timestamp is not None:
            self.verifications += 1
            if _check(entry.public_keys[0], raw[0], sdk_signed_bytes(env)):
                return Signer(entry.kid, entry.owner, entry.scopes, subset=True)
        raise SignatureInvalidError("signature does not verify")


@dataclass
class JwtVerifier:
    """Bearer-token checks with the receiver's clock; see the module docstring."""

    keys: dict[str, Any]
    audience: str | None = None
    issuer: str | None = None
    hs256_secret: bytes | None = None
    leeway_s: float = 0.0
    clock: Clock | None = None
    decodes: int = 0

    def check(self, token: str, expected_subject: str) -> dict[str, Any]:
        """Decode and validate; raises ``AUTH_FAILED`` (401) with a short reason."""
        self.decodes += 1
        try:
            header = jwt.get_unverified_header(token)
            alg = header.get("alg")
            if alg == "HS256" and self.hs256_secret is not None:
                key: Any = self.hs256_secret
            elif alg in ("EdDSA", "ES256"):
                key = self.keys.get(str(header.get("kid")))
                if key is None:
                    raise AuthFailedError("unknown token key")
                if alg == "ES256" and not isinstance(key, ec.EllipticCurvePublicKey):
                    raise AuthFailedError("token algorithm does not match its key")
                if alg == "EdDSA" and not isinstance(key, ed25519.Ed25519PublicKey):
                    raise AuthFailedError("token algorithm does not match its key")
            else:
                raise AuthFailedError("token algorithm not allowed")
            claims: dict[str, Any] = jwt.decode(
                token,
                key,
                algorithms=[alg],
                audience=self.audience,
                issuer=self.issuer,
                options={
                    "verify_exp": False,
                    "verify_nbf": False,
                    "verify_iat": False,
                    "require": ["exp", "sub"],
                    "verify_aud": self.audience is not None,
                    "verify_iss": self.issuer is not None,
                },
            )
        except jwt.PyJWTError as exc:
            raise AuthFailedError(f"invalid token: {type(exc).__name__}") from None
        now = resolve(self.clock).wall()
        exp = _time_claim(claims, "exp")
        if exp is None or now > exp + self.leeway_s:
            raise AuthFailedError("token expired")
        if "nbf" in claims:
            nbf = _time_claim(claims, "nbf")
            if nbf is None or now < nbf - self.leeway_s:
                raise AuthFailedError("token not yet valid")
        if claims.get("sub") != expected_subject:
            raise AuthFailedError("token subject does not own the signing key")
        return claims


def _time_claim(claims: dict[str, Any], name: str) -> float | None:
    """A NumericDate as finite float seconds, else None (refused by the caller).

    JSON from PyJWT may carry ``NaN``/``Infinity`` (Python's json accepts them) or an
    integer too large for a float: ``NaN`` compares false with everything, so an
    unchecked ``exp: NaN`` would never expire, and a huge integer would raise.
    """
    value = claims.get(name)
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        seconds = float(value)
    except OverflowError:
        return None
    return seconds if math.isfinite(seconds) else None


PrivateKey = ed25519.Ed25519PrivateKey | mldsa.MLDSA65PrivateKey | mldsa.MLDSA87PrivateKey


class SigningKey(Protocol):
    """What signs an envelope: a private key, or a key in a token
    (:class:`antireplay.keys.pkcs11.TokenSigner`)."""

    def sign(self, data: bytes, /) -> bytes: ...


def sign_envelope(
    message: dict[str, Any], kid: str, alg: str, keys: SigningKey | tuple[SigningKey, ...]
) -> dict[str, Any]:
    """Return ``message`` with a ``sig`` block over its canonical form (the sender's side).

    The message goes through the same parser the receiver uses, so both sides
    canonicalize identically.
    """
    private = keys if isinstance(keys, tuple) else (keys,)
    if alg not in ALGORITHMS or len(private) != len(ALGORITHMS[alg]):
        raise ValueError(f"unsupported algorithm {alg!r} for {len(private)} key(s)")
    unsigned = {k: v for k, v in message.items() if k != "sig"}
    raw = json.dumps(unsigned).encode()
    data = canonical_bytes(parse(raw, max_bytes=len(raw)))  # the receiver enforces its own limit
    value = ".".join(b64encode(key.sign(data)) for key in private)
    return {**unsigned, "sig": {"alg": alg, "kid": kid, "value": value}}


class SdkKeyPair(Protocol):
    """The RCAN SDK's ``rcan.signing.MLDSAKeyPair`` as far as signing needs it."""

    key_id: str

    def sign_bytes(self, data: bytes) -> bytes: ...


class UnsignedFieldsError(ValueError):
    """The message sets fields the SDK's signature does not cover (:func:`sign_sdk`)."""

    def __init__(self, fields: list[str]) -> None:
        super().__init__(f"the SDK signature does not cover {', '.join(fields)}")
        self.fields = fields


def sdk_target_problem(target: object) -> str | None:
    """Why the RCAN SDK could not read ``target`` (its own parser, ``RobotURI.parse``, which
    its ``RCANMessage.from_dict`` and so ``verify_message`` run), or ``None``."""
    from rcan.address import RobotURI  # noqa: PLC0415 - the SDK, only when signing for it
    from rcan.exceptions import RCANAddressError  # noqa: PLC0415

    if not isinstance(target, str):
        return "missing" if target is None else f"a string is needed, not {type(target).__name__}"
    try:
        RobotURI.parse(target)
    except RCANAddressError as exc:
        return str(exc)
    return None


def sign_sdk(message: dict[str, Any], key: mldsa.MLDSA65PrivateKey | SdkKeyPair) -> dict[str, Any]:
    """Sign ``message`` exactly as the RCAN SDK's ``sign_message`` does, so that the SDK's
    ``verify_message`` (and a receiver in ``sdk_compat`` mode) accepts it.

    The signature covers only the SDK's subset (:func:`~antireplay.rcan.envelope.sdk_signed_bytes`),
    so a message setting any other field is refused here (:class:`UnsignedFieldsError`)
    rather than sent with fields nobody signed, and so is a ``target`` the SDK cannot parse
    (``ValueError``: its ``verify_message`` would fail on it); ``kid`` is the SDK's key id
    (:func:`sdk_key_id`).
    """
    unsigned = {k: v for k, v in message.items() if k != "sig"}
    raw = json.dumps(unsigned).encode()
    env = parse(raw, max_bytes=len(raw))
    extra = unsigned_policy_fields(env)
    if extra:
        raise UnsignedFieldsError(extra)
    problem = sdk_target_problem(unsigned.get("target"))
    if problem is not None:
        raise ValueError(f"target: the RCAN SDK cannot read it ({problem})")
    data = sdk_signed_bytes(env)
    if isinstance(key, mldsa.MLDSA65PrivateKey):
        raw, kid = key.sign(data), sdk_key_id(key.public_key())
    else:
        raw, kid = key.sign_bytes(data), key.key_id
    value = base64.urlsafe_b64encode(raw).decode()
    return {**unsigned, "sig": {"alg": "ml-dsa-65", "kid": kid, "value": value}}


def write_key_pair(key: PrivateKey, private: Path, public: Path) -> None:
    """Write a PKCS#8 private key (created mode 0600, never overwritten) and its public key.

    Raises :class:`FileExistsError` if ``private`` exists: a key is never replaced silently.
    """
    pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    fd = os.open(private, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as handle:
        handle.write(pem)
    public.write_bytes(
        key.public_key().public_bytes(
            serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
        )
    )
