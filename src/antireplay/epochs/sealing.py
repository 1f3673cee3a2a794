"""Sealed topic samples, sans-I/O: the topic key, the sample framing and the judgment of one.

Theory of operation
-------------------
A sealed topic sends each sample as an epoch announcement (:mod:`.policy`) whose payload
is ``instance_len u16 | instance utf-8 | data`` (:func:`frame`), sealed under the topic
key ``HKDF(psk, info="antireplay/v1 dds topic" | domain | topic | type)`` (:func:`topic_key`):
a sample captured on one domain, topic or type fails the MAC on any other, and the
instance key is inside the MAC (the transport's key field is only a routing copy).

Judging is cheapest first.  :func:`check` looks at the length and the claimed instance
against the transport's key field: no crypto, no state.  The driver's verifier then opens
the announcement (MAC, freshness, order, the commit on its store); :func:`refused` turns
its typed rejection into a :class:`SampleVerdict` and :func:`accepted` decodes the data
(an authentic but undecodable sample is refused, never raised).  A fenced reader asks
writers for a fresh epoch; :class:`ChallengeTimer` says when (a new peer, or a retry
delay doubling up to a cap), from the monotonic time it is given.

Why here: this is the epoch protocol's framing for one use of it, transport-free, so it
lives in :mod:`antireplay.epochs` beside :mod:`.policy` (the only sibling it imports)
and below every adapter; Cyclone DDS (:mod:`antireplay.dds.topics`) is its driver.
import-linter forbids it the state, the audit trail, sockets, threads and the clock.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from antireplay.core.errors import (
    Code,
    EpochReplayedError,
    EpochTooFarAheadError,
    InvalidFrameError,
    MessageStaleError,
    ReplayAttackError,
    SignatureInvalidError,
    StateUnavailableError,
)
from antireplay.epochs.policy import (
    HEAD,
    KEY_RETIRED,
    LABELS,
    MAX_LEN,
    MIN_LEN,
    TAG_LEN,
    Announcement,
    FleetKey,
    Kind,
    hkdf32,
)

_ILEN = struct.Struct(">H")
#: The shortest sealed sample: an announcement carrying an empty instance and no data.
MIN_SAMPLE = MIN_LEN + _ILEN.size
MAX_INSTANCE = 256
#: Type name bound in the MAC for topics whose samples are raw bytes.
RAW = "octets"
#: Seconds between a fenced reader's challenges when no new peer matched (doubling up to the cap).
RETRY_S, RETRY_MAX_S = 0.25, 2.0
#: Outcomes whose MAC verified (refused only for freshness or order, or accepted).
AUTHENTIC = frozenset({"accepted", "replayed", "prefix_collision", "stale", "ahead", KEY_RETIRED})
#: Rejection class -> the outcome word counted and audited (prefix collisions are told apart).
OUTCOMES: dict[type[ReplayAttackError], str] = {
    InvalidFrameError: "malformed",
    SignatureInvalidError: "forged",
    MessageStaleError: "stale",
    EpochTooFarAheadError: "ahead",
    EpochReplayedError: "replayed",
    StateUnavailableError: "state_unavailable",
}


def topic_key(psk: bytes | FleetKey, topic: str, type_name: str, domain_id: int = 0) -> bytes:
    """The per-topic MAC secret: binds the domain id, the topic name and the type name, so a
    sample captured on one domain (one robot's ROS_DOMAIN_ID) fails the MAC on another."""
    info = b"antireplay/v1 dds topic"
    for part in (str(domain_id).encode(), topic.encode(), type_name.encode()):
        info += _ILEN.pack(len(part)) + part
    return hkdf32(psk, info)


def frame(instance: str, data: bytes) -> bytes:
    """The announcement payload of one sample: the instance key inside the MAC, then data."""
    raw = instance.encode()
    if len(raw) > MAX_INSTANCE:
        raise ValueError(f"instance key longer than {MAX_INSTANCE} bytes")
    return _ILEN.pack(len(raw)) + raw + data


def claim(sealed: bytes) -> tuple[bytes, int]:
    """The (nonce prefix, epoch) a sealed announcement claims; authenticated by nobody yet."""
    _, _, prefix, epoch = HEAD.unpack_from(sealed)
    return prefix, epoch


def claimed_instance(sealed: bytes) -> str | None:
    """The instance key inside the (not yet verified) payload, or None if unreadable."""
    start = HEAD.size
    (size,) = _ILEN.unpack_from(sealed, start)
    raw = sealed[start + _ILEN.size : start + _ILEN.size + size]
    if len(raw) != size or start + _ILEN.size + size > len(sealed) - TAG_LEN:
        return None
    try:
        return raw.decode()
    except UnicodeDecodeError:
        return None


@dataclass(frozen=True)
class SampleVerdict:
    """The judgment of one received sample (or datagram); only accepted ones carry ``value``."""

    outcome: str
    code: Code | None
    reason: str
    instance: str
    nonce_prefix: bytes | None = None
    epoch: int | None = None
    value: Any = None
    #: The machine detail of a refusal (``restart_fence``, ``key_retired``), if any.
    detail: str | None = None

    @property
    def accepted(self) -> bool:
        return self.code is None

    @property
    def authentic(self) -> bool:
        """True when the MAC verified (accepted, or refused only for freshness or order)."""
        return self.outcome in AUTHENTIC

    def named(self, noun: str) -> SampleVerdict:
        """This verdict with its reason naming what was refused (a topic's sealed value is
        an epoch announcement underneath; its reader calls it a ``sample``)."""
        head = LABELS[Kind.ANNOUNCEMENT]
        if not self.reason.startswith(head):
            return self
        return dataclasses.replace(self, reason=noun + self.reason[len(head) :])

    def line(self) -> str:
        """One printable line (what ``antireplay dds read`` prints)."""
        who = "-" if self.nonce_prefix is None else self.nonce_prefix.hex()
        head = "ACCEPTED" if self.accepted else f"REFUSED {self.code} {self.outcome}"
        shown = readable(self.value) if self.accepted else self.reason
        return f"{head} instance={self.instance!r} prefix={who} epoch={self.epoch} {shown!r}"


def readable(value: Any) -> Any:
    """Bytes that are UTF-8 as text (printed ``'move 1'``); other bytes stay bytes (their
    repr escapes them), other values as they are."""
    if isinstance(value, bytes):
        try:
            return value.decode()
        except UnicodeDecodeError:
            return value
    return value


def check(instance: str, sealed: bytes) -> SampleVerdict | None:
    """The refusal a sample earns before any crypto (length, the claimed instance against
    the key field), or None: it may go to the verifier.  Records nothing."""
    if not MIN_SAMPLE <= len(sealed) <= MAX_LEN:
        return SampleVerdict("malformed", Code.INVALID_FRAME, "bad sealed length", instance)
    if claimed_instance(sealed) != instance:
        prefix, epoch = claim(sealed)
        reason = "instance key does not match the sealed one"
        return SampleVerdict("wrong_instance", Code.INVALID_FRAME, reason, instance, prefix, epoch)
    return None


def refused(
    exc: ReplayAttackError, instance: str, sealed: bytes, *, collided: bool = False
) -> SampleVerdict:
    """The verdict for the verifier's typed rejection of ``sealed`` (``collided``: the
    verifier counted a prefix collision while judging it)."""
    prefix, epoch = claim(sealed)
    outcome = "prefix_collision" if collided else OUTCOMES.get(type(exc), "refused")
    if exc.detail == KEY_RETIRED:  # authentic, but under the fleet key that was rotated out
        outcome = KEY_RETIRED
    return SampleVerdict(outcome, exc.code, exc.reason, instance, prefix, epoch, detail=exc.detail)


def accepted(
    instance: str, opened: Announcement, decode: Callable[[bytes], Any] | None = None
) -> SampleVerdict:
    """The verdict for an announcement the verifier accepted: its data, decoded by
    ``decode`` when given (raw bytes otherwise); undecodable data is refused."""
    data = opened.payload[_ILEN.size + len(instance.encode()) :]
    if decode is not None:
        try:
            data = decode(data)
        except Exception:  # an authentic sender's undecodable sample: refused, not raised
            return SampleVerdict("malformed", Code.INVALID_FRAME, "undecodable data", instance)
    return SampleVerdict("accepted", None, "", instance, opened.nonce_prefix, opened.epoch, data)


class ChallengeTimer:
    """When a fenced reader sends its next challenge: at once when a new peer matched (it
    may answer), else when the retry delay ran out, the delay doubling up to the cap.
    Monotonic seconds in, a decision out; not safe for concurrent use."""

    def __init__(self, retry_s: float = RETRY_S, retry_max_s: float = RETRY_MAX_S) -> None:
        self.retry_s, self.retry_max_s = retry_s, retry_max_s
        self._peers, self._due, self._delay = -1, float("-inf"), retry_s

    def due(self, peers: int, now: float) -> bool:
        """Whether to challenge now, given how many ping peers matched; a yes re-arms."""
        new_peer = peers > self._peers
        if not new_peer and now < self._due:
            return False
        self._delay = self.retry_s if new_peer else min(2 * self._delay, self.retry_max_s)
        self._peers, self._due = peers, now + self._delay
        return True


__all__ = [
    "MAX_INSTANCE",
    "RAW",
    "ChallengeTimer",
    "SampleVerdict",
    "accepted",
    "check",
    "claim",
    "claimed_instance",
    "frame",
    "readable",
    "refused",
    "topic_key",
]
