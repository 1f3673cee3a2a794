"""Error codes, the exception family, and their wire mapping (HTTP status, COMMAND_NACK).

Theory of operation
-------------------
Errors are data.  Every rejection anywhere in antireplay is one of the stable
:class:`Code` values below; the code alone decides the HTTP status and the
NACK body, so an adapter never invents a status and a reader finds the whole
mapping in :data:`HTTP_STATUS`.  Exceptions carry the code, a short human
reason, and an optional machine ``detail`` (for example ``"watermark"`` when a
message is stale because the bounded cache had to forget older entries).

One code per event, one exception per code, named after it (``Code.X_Y`` is
raised as ``XYError``).  In particular, "the key is new to a bounded table and
at or below the fence its evictions raised (or, the table full, its lowest
mark)" is one event everywhere (a MAVLink stream, an epoch prefix):
``MESSAGE_STALE`` with ``detail="fence"`` (see
:class:`~antireplay.core.counters.FencedTable`); the store's restart fence is
``detail="restart_fence"``.  A session frame never brings a new key (only a
handshake does): a frame for a session the responder no longer holds, closed
or evicted, is ``SESSION_CLOSED``.  A frame from the wrong side of a link is
``WRONG_DIRECTION`` (MAVLink and sessions alike).  Events that are accepted but must be counted,
logged and audited are :class:`WarningCode` values, never bare strings.
``UPSTREAM_FAILED`` (502) answers a message that *was* accepted (its msg_id spent)
when the gateway's upstream failed; it is a COMMAND_NACK all the same, so the RCAN
SDK reads ``status: "error"``, never an ACK.

Rejections of a *message* derive from :class:`ReplayAttackError` (the name the
RCAN SDK uses for this family), so ``except ReplayAttackError`` catches every
verdict that should be answered with a COMMAND_NACK.  Operator mistakes
(:class:`ConfigError`) and a sender's own exhaustion (:class:`NonceExhaustedError`)
are separate: they are not answers to a peer.
"""

from __future__ import annotations

from typing import Any, Literal

from antireplay.core.messages import StrEnum


class Code(StrEnum):
    """Stable rejection codes; the string value is what goes on the wire."""

    REPLAY_DETECTED = "REPLAY_DETECTED"
    MESSAGE_STALE = "MESSAGE_STALE"
    MESSAGE_FROM_FUTURE = "MESSAGE_FROM_FUTURE"
    INVALID_TIMESTAMP = "INVALID_TIMESTAMP"
    INVALID_MESSAGE_ID = "INVALID_MESSAGE_ID"
    INVALID_ENVELOPE = "INVALID_ENVELOPE"
    INVALID_FRAME = "INVALID_FRAME"
    VERSION_INCOMPATIBLE = "VERSION_INCOMPATIBLE"
    PAYLOAD_TOO_LARGE = "PAYLOAD_TOO_LARGE"
    UNSUPPORTED_MEDIA_TYPE = "UNSUPPORTED_MEDIA_TYPE"
    AUTH_FAILED = "AUTH_FAILED"
    SIGNATURE_INVALID = "SIGNATURE_INVALID"
    SIGNATURE_REQUIRED = "SIGNATURE_REQUIRED"
    UNKNOWN_SENDER = "UNKNOWN_SENDER"
    KEY_REVOKED = "KEY_REVOKED"
    KEY_EXPIRED = "KEY_EXPIRED"
    KEY_NOT_YET_VALID = "KEY_NOT_YET_VALID"
    SCOPE_DENIED = "SCOPE_DENIED"
    WRONG_TARGET = "WRONG_TARGET"
    INVALID_COUNTER = "INVALID_COUNTER"
    COUNTER_REPLAYED = "COUNTER_REPLAYED"
    COUNTER_TOO_OLD = "COUNTER_TOO_OLD"
    COUNTER_EXHAUSTED = "COUNTER_EXHAUSTED"
    EPOCH_REPLAYED = "EPOCH_REPLAYED"
    EPOCH_TOO_FAR_AHEAD = "EPOCH_TOO_FAR_AHEAD"
    SESSION_CLOSED = "SESSION_CLOSED"
    UNKNOWN_SESSION = "UNKNOWN_SESSION"
    STATE_UNAVAILABLE = "STATE_UNAVAILABLE"
    WRONG_DIRECTION = "WRONG_DIRECTION"
    UPSTREAM_FAILED = "UPSTREAM_FAILED"


#: The one place where a code becomes an HTTP status.
HTTP_STATUS: dict[Code, int] = {
    Code.REPLAY_DETECTED: 409,
    Code.MESSAGE_STALE: 408,
    Code.MESSAGE_FROM_FUTURE: 400,
    Code.INVALID_TIMESTAMP: 400,
    Code.INVALID_MESSAGE_ID: 400,
    Code.INVALID_ENVELOPE: 400,
    Code.INVALID_FRAME: 400,
    Code.VERSION_INCOMPATIBLE: 426,
    Code.PAYLOAD_TOO_LARGE: 413,
    Code.UNSUPPORTED_MEDIA_TYPE: 415,
    Code.AUTH_FAILED: 401,
    Code.SIGNATURE_INVALID: 401,
    Code.SIGNATURE_REQUIRED: 401,
    Code.UNKNOWN_SENDER: 401,
    Code.KEY_REVOKED: 401,
    Code.KEY_EXPIRED: 401,
    Code.KEY_NOT_YET_VALID: 401,
    Code.SCOPE_DENIED: 403,
    Code.WRONG_TARGET: 403,
    Code.INVALID_COUNTER: 400,
    Code.COUNTER_REPLAYED: 409,
    Code.COUNTER_TOO_OLD: 408,
    Code.COUNTER_EXHAUSTED: 409,
    Code.EPOCH_REPLAYED: 409,
    Code.EPOCH_TOO_FAR_AHEAD: 400,
    Code.SESSION_CLOSED: 401,
    Code.UNKNOWN_SESSION: 401,
    Code.STATE_UNAVAILABLE: 503,
    Code.WRONG_DIRECTION: 403,
    Code.UPSTREAM_FAILED: 502,
}


class WarningCode(StrEnum):
    """Stable codes of events that are accepted but must be counted, logged and audited."""

    #: A duplicate that passed anyway (a fresh ESTOP; see :mod:`antireplay.core.window`).
    REPLAY_DETECTED = "REPLAY_DETECTED"
    #: A fresh ESTOP admitted while the replay state could not be reached.
    STATE_UNAVAILABLE = "STATE_UNAVAILABLE"
    #: A fresh ESTOP delivered while its audit row could not be written (held, written later).
    AUDIT_UNAVAILABLE = "AUDIT_UNAVAILABLE"
    #: An epoch sender moved to its successor prefix after a forward clock glitch.
    EPOCH_SENDER_ROTATED = "EPOCH_SENDER_ROTATED"
    #: A second DDS relay publishes under this relay's service name.
    DUPLICATE_SERVICE_NAME = "DUPLICATE_SERVICE_NAME"
    #: The replay store may have lost data; a fence now refuses what it may have forgotten.
    STATE_LOST = "STATE_LOST"


#: COMMAND_NACK in the current canonical RCAN numbering; 31 was its number in RCAN v1.5/v1.6.
NACK_TYPE_CURRENT = 18
NACK_TYPE_LEGACY = 31
COMMAND_ACK = 17
#: The robot URI an answer names as its ``target`` (the RCAN SDK's ``RCANMessage.from_dict``
#: parses ``target`` as one); answers are not addressed to anyone the receiver has verified.
ANSWER_TARGET = "rcan://local/antireplay/receiver/v1/gateway"
ANSWER_RCAN = "3.2"


def _sdk_fields(cmd: str, status: str) -> dict[str, Any]:
    """The constant fields the RCAN SDK's classes read an answer with:
    ``RCANMessage.from_dict`` needs ``rcan``, ``cmd`` and a robot-URI ``target``;
    ``RCANResponse.from_dict`` takes ``status`` (and ``msg_id``, ``message``, set per
    answer: the answered message's msg_id, or ``""``, and the reason)."""
    return {
        "rcan": ANSWER_RCAN,
        "rcan_version": ANSWER_RCAN,
        "cmd": cmd,
        "target": ANSWER_TARGET,
        "status": status,
    }


_NACK_FIELDS = _sdk_fields("COMMAND_NACK", "error")
_ACK_FIELDS = _sdk_fields("COMMAND_ACK", "ok")


def command_ack(msg_id: str | None, warning: str | None = None) -> dict[str, Any]:
    """The COMMAND_ACK (type 17) answering an accepted message; the SDK reads it as
    ``RCANResponse`` with ``status == "ok"`` (``msg_id`` sanitized by the caller)."""
    body: dict[str, Any] = {"type": COMMAND_ACK, "accepted": True, "ref_msg_id": msg_id}
    if warning is not None:
        body["warning"] = warning
    message = "accepted" if warning is None else f"accepted with warning {warning}"
    return {**body, **_ACK_FIELDS, "msg_id": msg_id or "", "message": message}


class AntiReplayError(Exception):
    """Base of every antireplay exception."""


class ReplayAttackError(AntiReplayError):
    """A message was rejected; carries the code, HTTP status and a short reason."""

    code: Code = Code.INVALID_ENVELOPE

    def __init__(self, reason: str, *, detail: str | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.detail = detail

    def __str__(self) -> str:
        return f"{self.code}: {self.reason}"

    @property
    def coded_reason(self) -> str:
        """The reason as a NACK carries it, led by its code (``REPLAY_DETECTED: …``)."""
        return f"{self.code}: {self.reason}"

    @property
    def http_status(self) -> int:
        """HTTP status for HTTP transports (see :data:`HTTP_STATUS`)."""
        return HTTP_STATUS[self.code]

    def to_nack(self, msg_id: str | None, *, nack_type: int = NACK_TYPE_CURRENT) -> dict[str, Any]:
        """The COMMAND_NACK body answering the rejected message: ``type``, ``code``,
        ``ref_msg_id``, ``reason`` (and ``detail``) for RCAN §8.3, plus what the RCAN SDK's
        ``RCANMessage.from_dict`` and ``RCANResponse.from_dict`` read (``status: "error"``,
        ``message`` = the reason, ``msg_id`` = ``ref_msg_id`` or ``""``).  The reason starts
        with the code (:attr:`coded_reason`): the SDK's ``RCANResponse`` keeps only ``message``.

        ``msg_id`` must already be sanitized by the caller when it came from an
        unauthenticated peer; the NACK never echoes the payload.
        """
        reason = self.coded_reason
        body: dict[str, Any] = {
            "type": nack_type,
            "code": str(self.code),
            "ref_msg_id": msg_id,
            "reason": reason,
            **_NACK_FIELDS,
            "msg_id": msg_id or "",
            "message": reason,
        }
        if self.detail is not None:
            body["detail"] = self.detail
        return body


class ReplayDetectedError(ReplayAttackError):
    """The msg_id was already accepted and its message could still pass the freshness test."""

    code = Code.REPLAY_DETECTED


class MessageStaleError(ReplayAttackError):
    """The message cannot be proven fresh: older than its window, or at or below a
    watermark or fence (``detail`` says which: ``watermark``, ``restart_fence``, ``fence``)."""

    code = Code.MESSAGE_STALE


class MessageFromFutureError(ReplayAttackError):
    """The message is stamped further ahead than the allowed clock skew."""

    code = Code.MESSAGE_FROM_FUTURE


class InvalidTimestampError(ReplayAttackError):
    """The timestamp is not finite, non-negative Unix seconds."""

    code = Code.INVALID_TIMESTAMP


class InvalidMessageIdError(ReplayAttackError):
    """The msg_id is not a non-empty string of at most 128 characters."""

    code = Code.INVALID_MESSAGE_ID


class InvalidEnvelopeError(ReplayAttackError):
    """The bytes are not a well-formed RCAN envelope."""

    code = Code.INVALID_ENVELOPE


class PayloadTooLargeError(ReplayAttackError):
    """The body is larger than the transport's limit (refused before parsing)."""

    code = Code.PAYLOAD_TOO_LARGE


class UnsupportedMediaTypeError(ReplayAttackError):
    """The body's declared media type is not one this transport parses."""

    code = Code.UNSUPPORTED_MEDIA_TYPE


class VersionIncompatibleError(ReplayAttackError):
    """The envelope's RCAN version is not one this receiver speaks."""

    code = Code.VERSION_INCOMPATIBLE


class AuthFailedError(ReplayAttackError):
    """The bearer token (JWT) is missing, invalid, expired or for someone else."""

    code = Code.AUTH_FAILED


class ScopeDeniedError(ReplayAttackError):
    """The authenticated sender may not do this."""

    code = Code.SCOPE_DENIED


class InvalidFrameError(ReplayAttackError):
    """A binary frame (session frame, epoch announcement, ping) is malformed."""

    code = Code.INVALID_FRAME


class SignatureInvalidError(ReplayAttackError):
    """A MAC or signature did not verify."""

    code = Code.SIGNATURE_INVALID


class SignatureRequiredError(ReplayAttackError):
    """The message carries no signature and its type is not allowed unsigned."""

    code = Code.SIGNATURE_REQUIRED


class UnknownSenderError(ReplayAttackError):
    """The message names a key or identity this receiver does not know."""

    code = Code.UNKNOWN_SENDER


class KeyRevokedError(ReplayAttackError):
    """The message names a key on the revocation list (``antireplay keys revoke``)."""

    code = Code.KEY_REVOKED


class KeyExpiredError(ReplayAttackError):
    """The message names a key past its ``not_after``."""

    code = Code.KEY_EXPIRED


class KeyNotYetValidError(ReplayAttackError):
    """The message names a key before its ``not_before``."""

    code = Code.KEY_NOT_YET_VALID


class WrongTargetError(ReplayAttackError):
    """A message is addressed to another receiver (another vehicle).  A signed frame is
    bound only after its signature verified; an allow-listed unsigned one is not authentic."""

    code = Code.WRONG_TARGET


class InvalidCounterError(ReplayAttackError):
    """The counter is not a non-negative integer."""

    code = Code.INVALID_COUNTER


class CounterReplayedError(ReplayAttackError):
    """The counter was already accepted on this stream."""

    code = Code.COUNTER_REPLAYED


class CounterTooOldError(ReplayAttackError):
    """The counter fell behind the sliding window; it cannot be proven fresh."""

    code = Code.COUNTER_TOO_OLD


class CounterExhaustedError(ReplayAttackError):
    """The peer's counter is at or above the limit: the session must be rekeyed."""

    code = Code.COUNTER_EXHAUSTED


class EpochReplayedError(ReplayAttackError):
    """The epoch is not greater than the last one accepted from that prefix."""

    code = Code.EPOCH_REPLAYED


class EpochTooFarAheadError(ReplayAttackError):
    """An authentic epoch jumped further ahead than ``max_forward_s`` allows."""

    code = Code.EPOCH_TOO_FAR_AHEAD


class SessionClosedError(ReplayAttackError):
    """The frame's session was issued but is no longer held (closed after a rekey, or
    evicted), its keys gone with it; only a new handshake helps."""

    code = Code.SESSION_CLOSED


class UnknownSessionError(ReplayAttackError):
    """The frame names a session this receiver never opened."""

    code = Code.UNKNOWN_SESSION


class WrongDirectionError(ReplayAttackError):
    """A frame claims to come from the wrong side of a link (a reflection).  Checked
    before any signature, so the claim itself is not authenticated; the frame is only
    dropped."""

    code = Code.WRONG_DIRECTION


class StateUnavailableError(ReplayAttackError):
    """The replay state store cannot be reached; fail closed."""

    code = Code.STATE_UNAVAILABLE


class UpstreamFailedError(ReplayAttackError):
    """An accepted message's upstream call failed.  Its msg_id stays spent (the upstream
    may have acted before failing); ``delivered`` says ``"no"`` (the upstream was never
    reached: nothing ran), ``"unknown"`` (sent, then failed or timed out: it may have
    run) or ``"yes"`` (it answered with an HTTP error status).  The sender repeats the
    action, if it still wants it, under a new msg_id."""

    code = Code.UPSTREAM_FAILED

    def __init__(self, failure: str, *, delivered: Literal["no", "unknown", "yes"]) -> None:
        self.delivered = delivered
        super().__init__(
            f"upstream failed ({failure}); delivered: {self.delivered}; this msg_id is spent,"
            " send the action again under a new msg_id",
            detail=f"delivered={self.delivered}",
        )

    def to_nack(self, msg_id: str | None, *, nack_type: int = NACK_TYPE_CURRENT) -> dict[str, Any]:
        """The COMMAND_NACK, plus ``delivered`` (``"no"``, ``"unknown"`` or ``"yes"``)."""
        return {**super().to_nack(msg_id, nack_type=nack_type), "delivered": self.delivered}


class ConfigError(AntiReplayError, ValueError):
    """Invalid configuration; names the key, the value and what is allowed. Never clamped."""

    def __init__(
        self, key: str, value: object, allowed: str, *, message: str | None = None
    ) -> None:
        super().__init__(message or f"invalid config {key}={value!r}: allowed {allowed}")
        self.key = key
        self.value = value
        self.allowed = allowed

    @classmethod
    def file_not_found(cls, key: str, path: str) -> ConfigError:
        """A file the configuration names is not there: said in those words."""
        return cls(key, path, "an existing file", message=f"{key}: file not found: {path}")


class NonceExhaustedError(AntiReplayError):
    """This sender's own counter, epoch or timestamp reached its limit; rekey instead of
    wrapping.  Not an answer to a peer (a peer's exhausted counter is ``COUNTER_EXHAUSTED``)."""


class StateFileError(AntiReplayError):
    """A state, key or audit file is unusable (corrupt, wrong-typed, foreign, truncated,
    rolled back or in use); refuse to start, naming the file and the recovery command."""

    what = "state file"

    def __init__(self, path: str, problem: str, *, recovery: str | None = None) -> None:
        self.path = path
        self.problem = problem
        self.recovery = recovery if recovery is not None else f"antireplay state repair {path}"
        super().__init__(
            f"{self.what} {path}: {problem}; refusing to start. Recover with: {self.recovery}"
        )


class AuditFileError(StateFileError):
    """The audit trail, its head checkpoint or its head key is unusable or was tampered with."""

    what = "audit file"
