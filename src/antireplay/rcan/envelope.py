"""The RCAN JSON envelope: strict parsing and the canonical signing bytes.

Theory of operation
-------------------
``parse`` turns untrusted bytes into an :class:`Envelope` or raises
``INVALID_ENVELOPE`` with a reason; nothing else ever escapes.  msgspec does
the typed decoding (about a microsecond), after a size check (default 64 KiB)
and before a depth check (default 16 levels of nesting).

Field policy: the fields the official RCAN SDK emits (``RCANMessage.to_dict``),
plus ``type``, ``safety_event``, ``timestamp_ms`` and ``jwt``, are known;
**any other field is rejected**, so two parsers can never disagree about a
field one of them ignored.  Exactly one of ``timestamp`` (Unix seconds) and
``timestamp_ms`` (integer milliseconds, the SDK's safety-message unit) must be
present.  ``msg_id`` and the timestamp's *value* are judged by the window
(``INVALID_MESSAGE_ID`` / ``INVALID_TIMESTAMP``), not here.

Everything a peer controls gets a typed answer, never an exception: bytes that
are not UTF-8 (JSON text must be, RFC 8259 §8.1) are ``INVALID_ENVELOPE``
(whatever msgspec's version raises for them, inside ``sig`` too); an integer
timestamp beyond the 64-bit range is ``INVALID_TIMESTAMP`` here, so the window
is never handed a number it cannot convert to a float; and the integer fields
(``type``, ``qos``, ``sequence_number``, ``loa``) are bounded in the schema, so
no store or audit column meets an integer it cannot hold.

Canonical form (what signatures cover): the envelope as decoded, **minus
``sig`` and ``jwt``**, encoded as JSON with keys sorted, no whitespace, UTF-8,
and numbers as Python's shortest round-trip repr.  It covers every field that
affects policy (type, scope, qos, target, safety_event, timestamp, msg_id,
params, sender, …), so none can be changed without breaking the signature.
Duplicate JSON keys resolve to the last one; the gateway forwards the
canonical re-encoding, never the raw bytes, so no downstream parser sees a
different message than the one that was verified.

``sdk_signed_bytes`` reproduces the official SDK's subset for the
compatibility mode.  In rcan 3.7.0, ``rcan.signing.sign_message`` signs
``_canonical_message_bytes``: exactly ``rcan, msg_id, timestamp, cmd, target,
params`` (sorted-key JSON, ``target`` as a string) and nothing else
(:data:`SDK_SIGNED_FIELDS`).  Everything else ``RCANMessage.to_dict`` can emit
is unsigned: ``rcan_version, confidence, sender, scope, sender_type,
cloud_provider, key_id, qos, sequence_number, delegation_chain, group_id,
read_only, presence_verified, proximity_m, loa, transport_encoding,
firmware_hash, attestation_ref`` (and our ``type``, ``safety_event``,
``timestamp_ms``).  :func:`unsigned_policy_fields` names those a message sets; the
pipeline refuses such a message, so in compatibility mode only signed content
is authorized and forwarded.  Two exceptions: ``rcan_version``, which the SDK
always emits as a mirror of ``rcan``, passes when empty or equal to the signed
``rcan`` (then it says nothing unsigned); and ``qos``, the SDK's delivery hint
(its ``make_estop_with_qos`` sets 2), is tolerated but read by no policy and
removed before forwarding (:func:`without_delivery_hints`).

Safety commands: the SDK has no signed way to say SAFETY (its ``type``,
``safety_event`` and ``qos`` are unsigned; ``rcan.safety.make_estop_message``
builds an unsigned dict), but its signature covers ``cmd``.  So a COMMAND (or
SAFETY) message whose ``cmd`` is exactly ``ESTOP``, ``STOP`` or ``RESUME``
(upper case, :data:`SAFETY_COMMANDS`) *is* a SAFETY message with that event
(:func:`safety_class`): the 10 s safety window, the ``safety`` scope and the
ESTOP invariant apply, derived only from a signed field, for SDK and full
signatures alike.  A ``safety_event`` field or parameter that contradicts such
a ``cmd`` is ``INVALID_ENVELOPE``; any other ``cmd`` (``estop``, ``halt``)
is an ordinary command unless ``type``/``safety_event`` say otherwise.  A
``safety_event`` field must name a :class:`~antireplay.core.messages.SafetyEvent` and
sit on a SAFETY message (``type`` 6, or a safety ``cmd``); anything else is
``INVALID_ENVELOPE``, so no upstream is ever handed an event no rule here applied.
"""

from __future__ import annotations

import json
from typing import Annotated, Any

import msgspec

from antireplay.core.errors import InvalidEnvelopeError, InvalidTimestampError
from antireplay.core.messages import MessageType, SafetyEvent

MAX_BYTES = 64 * 1024
MAX_DEPTH = 16
#: Integer timestamps (seconds or milliseconds) beyond this are refused before any conversion.
MAX_INT_TIMESTAMP = 2**63 - 1
#: Bounded integer fields: what a SQLite INTEGER (and any int64 upstream) can hold.
Int64 = Annotated[int, msgspec.Meta(ge=-(2**63), le=2**63 - 1)]


class Signature(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """``sig``: algorithm, key id, base64url value."""

    alg: str
    kid: str
    value: str


class Envelope(msgspec.Struct, forbid_unknown_fields=True, frozen=True, omit_defaults=True):
    """An RCAN message as the SDK's ``to_dict`` emits it, plus typed-message fields."""

    msg_id: Any
    cmd: str
    target: str
    rcan: str = ""
    rcan_version: str = ""
    timestamp: Any = None
    timestamp_ms: Any = None
    type: Int64 = int(MessageType.COMMAND)
    safety_event: str | None = None
    params: dict[str, Any] = msgspec.field(default_factory=dict)
    sender: str | None = None
    scope: str | None = None
    # Kept raw and decoded only at the signature step: a replay never pays for it.
    sig: msgspec.Raw = msgspec.field(default_factory=msgspec.Raw)
    key_id: str | None = None
    qos: Int64 = 0
    jwt: str | None = None
    confidence: float | None = None
    sender_type: str | None = None
    cloud_provider: str | None = None
    sequence_number: Int64 | None = None
    delegation_chain: list[Any] = msgspec.field(default_factory=list)
    group_id: str | None = None
    read_only: bool = False
    presence_verified: bool = False
    proximity_m: float | None = None
    loa: Int64 | None = None
    transport_encoding: str | None = None
    firmware_hash: str | None = None
    attestation_ref: str | None = None

    def signature(self) -> Signature | None:
        """The ``sig`` block, decoded now; a malformed one is ``INVALID_ENVELOPE``."""
        if not self.sig:
            return None
        try:
            return _SIG_DECODER.decode(self.sig)
        except msgspec.ValidationError as exc:
            raise InvalidEnvelopeError(f"sig: {_short(str(exc))}") from None
        except (msgspec.DecodeError, UnicodeDecodeError) as exc:
            raise InvalidEnvelopeError(f"sig: {_decode_failure(self.sig, exc)}") from None

    @property
    def seconds(self) -> object:
        """The timestamp in seconds (``timestamp_ms`` converted exactly), still unvalidated."""
        if self.timestamp_ms is not None:
            ms = self.timestamp_ms
            if isinstance(ms, bool) or not isinstance(ms, int):
                return ms  # the window rejects it with INVALID_TIMESTAMP
            return ms / 1000
        return self.timestamp


_DECODER = msgspec.json.Decoder(Envelope)
_SIG_DECODER = msgspec.json.Decoder(Signature)
_ENCODER = msgspec.json.Encoder()


def _decode_failure(raw: bytes | bytearray | memoryview, exc: Exception) -> str:
    """One stable reason for bytes that are not UTF-8, whatever msgspec's version says.

    msgspec up to 0.22 raised a bare ``UnicodeDecodeError``, 0.23 a ``DecodeError``
    with its own wording; the UTF-8 test runs only on this failure path.
    """
    try:
        bytes(raw).decode("utf-8")
    except UnicodeDecodeError:
        return "not UTF-8"
    return f"not JSON: {_short(str(exc))}"


def parse(raw: bytes, *, max_bytes: int = MAX_BYTES, max_depth: int = MAX_DEPTH) -> Envelope:
    """Strictly decode one envelope; every failure is ``INVALID_ENVELOPE`` with a reason."""
    if not isinstance(raw, bytes | bytearray | memoryview):
        raise InvalidEnvelopeError("body must be bytes")
    if len(raw) > max_bytes:
        raise InvalidEnvelopeError(f"envelope larger than {max_bytes} bytes")
    try:
        env = _DECODER.decode(raw)
    except msgspec.ValidationError as exc:
        reason = _short(str(exc))
        hint = _SAFETY_DICT_HINT if "`message_type`" in reason else ""
        raise InvalidEnvelopeError(f"schema: {reason}{hint}") from None
    except (msgspec.DecodeError, UnicodeDecodeError) as exc:
        raise InvalidEnvelopeError(_decode_failure(raw, exc)) from None
    except RecursionError:
        raise InvalidEnvelopeError("nested too deeply") from None
    if (env.timestamp is None) == (env.timestamp_ms is None):
        raise InvalidEnvelopeError("exactly one of timestamp and timestamp_ms is required")
    for stamp in (env.timestamp, env.timestamp_ms):
        if type(stamp) is int and not -MAX_INT_TIMESTAMP <= stamp <= MAX_INT_TIMESTAMP:
            raise InvalidTimestampError("timestamp out of range")
    if env.cmd in SAFETY_COMMANDS:
        _check_safety_command(env)
    if env.safety_event is not None:
        _check_safety_event(env)
    deep = _nested(env.params) or bool(env.delegation_chain)
    if deep and max(_depth(env.params), _depth(env.delegation_chain)) > max_depth:
        raise InvalidEnvelopeError(f"nested deeper than {max_depth} levels")
    return env


#: Signed commands that are safety messages (module docstring, "Safety commands").
SAFETY_COMMANDS = frozenset(str(event) for event in SafetyEvent)
_SAFETY = int(MessageType.SAFETY)
_SAFETY_TYPES = frozenset({int(MessageType.COMMAND), _SAFETY})


def safety_class(env: Envelope) -> tuple[int, str | None]:
    """The message type and safety event the window and the scopes apply: a COMMAND (or
    a SAFETY message) whose ``cmd`` is ``ESTOP``, ``STOP`` or ``RESUME`` is SAFETY with
    that event; anything else is what its ``type`` and ``safety_event`` say."""
    if env.cmd in SAFETY_COMMANDS and env.type in _SAFETY_TYPES:
        return _SAFETY, env.cmd
    return env.type, env.safety_event


def _check_safety_command(env: Envelope) -> None:
    """A safety command names its event once: a ``safety_event`` (field or parameter)
    that says otherwise is ambiguous, and refused rather than guessed."""
    if env.type not in _SAFETY_TYPES:
        return
    for said in (env.safety_event, env.params.get("safety_event")):
        if said is not None and said != env.cmd:
            raise InvalidEnvelopeError(f"cmd {env.cmd} contradicts its safety_event")


def _check_safety_event(env: Envelope) -> None:
    """A ``safety_event`` is one of :class:`SafetyEvent` and only on a SAFETY message: on
    anything else an upstream might act on a field no rule here applied."""
    if env.safety_event not in SAFETY_COMMANDS:
        raise InvalidEnvelopeError(
            f"safety_event must be one of {', '.join(sorted(SAFETY_COMMANDS))}"
        )
    if safety_class(env)[0] != _SAFETY:
        raise InvalidEnvelopeError(
            f"safety_event on a type {env.type} message: only a SAFETY (type {_SAFETY}) "
            "message carries one"
        )


#: ``rcan.safety.make_estop_message`` builds an unsigned dict (``message_type``, ``ruri``):
#: nothing a receiver may act on; the refusal says what to send instead.
_SAFETY_DICT_HINT = (
    " (an rcan.safety message is unsigned: send a signed RCANMessage with cmd ESTOP, STOP"
    " or RESUME)"
)


def _short(text: str) -> str:
    """Error reasons are capped and never echo more than a hint of attacker input."""
    return text[:120]


def _nested(params: dict[str, Any]) -> bool:
    """Fast path: flat params (the common case) cannot be too deep."""
    return any(type(v) is dict or type(v) is list for v in params.values())


def _depth(value: object, level: int = 1) -> int:
    if level > MAX_DEPTH + 1:
        return level
    if isinstance(value, dict):
        return max((_depth(v, level + 1) for v in value.values()), default=level)
    if isinstance(value, list):
        return max((_depth(v, level + 1) for v in value), default=level)
    return level


def canonical_bytes(env: Envelope) -> bytes:
    """The bytes every signature covers: all fields except ``sig`` and ``jwt``."""
    body = msgspec.to_builtins(env, builtin_types=(msgspec.Raw,))
    body.pop("sig", None)
    body.pop("jwt", None)
    return json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()


def encode(env: Envelope) -> bytes:
    """The envelope as forwarded upstream (what was verified, with its signature).

    ``sig`` is re-encoded from its decoded form, never copied raw: duplicate keys,
    odd whitespace or bytes no downstream parser expects stay at the gateway.
    """
    sig = env.signature()
    if sig is None:
        body = msgspec.to_builtins(env, builtin_types=(msgspec.Raw,))
        body.pop("sig", None)
        return _ENCODER.encode(body)
    return _ENCODER.encode(msgspec.structs.replace(env, sig=msgspec.Raw(_ENCODER.encode(sig))))


def sdk_signed_bytes(env: Envelope) -> bytes:
    """The official RCAN SDK's canonical subset (``rcan.signing._canonical_message_bytes``)."""
    payload = {
        "rcan": env.rcan,
        "msg_id": env.msg_id,
        "timestamp": env.timestamp,
        "cmd": env.cmd,
        "target": env.target,
        "params": env.params,
    }
    return json.dumps(payload, sort_keys=True, separators=(",", ":")).encode()


#: What the rcan 3.7.0 SDK signature covers (``rcan.signing._canonical_message_bytes``).
SDK_SIGNED_FIELDS = frozenset({"rcan", "msg_id", "timestamp", "cmd", "target", "params"})
#: Authenticated on their own (``sig`` is the signature; a ``jwt`` is verified separately).
_SELF_AUTHENTICATED = frozenset({"sig", "jwt"})
#: Unsigned delivery hints the SDK sets (``make_estop_with_qos``: ``qos=2``): tolerated,
#: read by no policy, and removed before forwarding (:func:`without_delivery_hints`).
SDK_DELIVERY_HINTS = frozenset({"qos"})
_DEFAULTS = Envelope(msg_id="", cmd="", target="", timestamp=0)


def unsigned_policy_fields(env: Envelope) -> list[str]:
    """Fields set on ``env`` that the SDK's signature does not cover (module docstring)."""
    unsigned = []
    for name in env.__struct_fields__:
        if name in SDK_SIGNED_FIELDS or name in _SELF_AUTHENTICATED or name in SDK_DELIVERY_HINTS:
            continue
        value = getattr(env, name)
        if name == "rcan_version":
            if value not in ("", env.rcan):
                unsigned.append(name)
        elif value != getattr(_DEFAULTS, name):
            unsigned.append(name)
    return unsigned


def without_delivery_hints(env: Envelope) -> Envelope:
    """``env`` minus the unsigned delivery hints (what an SDK-signed message forwards)."""
    return msgspec.structs.replace(env, qos=_DEFAULTS.qos) if env.qos != _DEFAULTS.qos else env
