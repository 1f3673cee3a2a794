"""The RCAN receive core: RCAN §8.3's steps as values in, decisions out (sans-I/O).

Theory of operation
-------------------
:class:`Steps` holds no lock, reads no clock, touches no store, log or audit trail; a
driver (:class:`~antireplay.rcan.receive.Receiver`, one thread driver and one asyncio
driver) performs every I/O between its calls, cheapest step first:

1-2. :meth:`Steps.parse`: size, depth, schema, RCAN version, and the message's class
     (:func:`~antireplay.rcan.envelope.safety_class`, computed once and carried):
     :class:`Checked`, or :class:`Done` (a refusal).
3.   the driver runs the replay check, a store read that records nothing
     (:meth:`~antireplay.state.replay.ReplayCache.check`), and hands its refusal if any to
4-6. :meth:`Steps.authenticate`: bearer token, signature, scopes: :class:`NeedsCommit`
     or :class:`Done`.  A ``REPLAY_DETECTED`` that may be a QoS retransmission
     (:func:`may_retry`) has its token checked first: its answer has content.
7.   the driver performs the one atomic commit (``ReplayCache.commit`` or
     ``commit_async``), then :meth:`Steps.accept` (or :meth:`Steps.refuse`) builds the
     :class:`Outcome` and :func:`audit_row` the row the driver queues.

What is SAFETY/ESTOP is decided from signed fields only (envelope.py), so nobody can
turn a captured command into an exempt ESTOP; an SDK signer's unsigned ``qos`` hint is
removed from the accepted envelope (nothing unsigned is forwarded).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from antireplay.audit import AuditRow, sanitize
from antireplay.core.errors import (
    AuthFailedError,
    Code,
    ReplayAttackError,
    ScopeDeniedError,
    VersionIncompatibleError,
    command_ack,
)
from antireplay.core.messages import MessageType
from antireplay.core.settings import SecurityConfig
from antireplay.core.window import Verdict
from antireplay.rcan.answers import Entry, HeldAnswer, digest
from antireplay.rcan.auth import JwtVerifier, KeyRegistry, Signer
from antireplay.rcan.envelope import (
    Envelope,
    parse,
    safety_class,
    unsigned_policy_fields,
    without_delivery_hints,
)

#: A message's class: the type and safety event the window and the scopes apply.
MessageClass = tuple[int, str | None]


@dataclass(slots=True)
class Outcome:
    """What happened to one message, ready for any transport."""

    accepted: bool
    status: int
    code: str | None = None
    reason: str | None = None
    warning: str | None = None
    msg_id: str | None = None
    envelope: Envelope | None = None
    signer: Signer | None = None
    error: ReplayAttackError | None = None
    nack_type: int = 18
    #: A QoS retransmission's answer: the original's, marked duplicate; the transport sends
    #: it as is (the outcome is not accepted: nothing runs again; ``status`` and ``nack``
    #: say 409 ``REPLAY_DETECTED``, detail ``QOS_RETRY``).  ``None`` normally.
    retry: HeldAnswer | None = None
    #: The message type the policy applied (its class, as audited); ``None`` if unparsed.
    msg_type: int | None = None

    @property
    def nack(self) -> dict[str, Any] | None:
        """The COMMAND_NACK answering a rejection (built on demand)."""
        if self.error is None:
            return None
        return self.error.to_nack(self.msg_id, nack_type=self.nack_type)

    @property
    def ack(self) -> dict[str, Any] | None:
        """The COMMAND_ACK answering an accepted message (built on demand)."""
        return command_ack(self.msg_id, self.warning) if self.accepted else None


@dataclass(frozen=True, slots=True)
class Checked:
    """Steps 1-2 passed: the driver runs the replay check on ``env``, then authenticates."""

    env: Envelope
    cls: MessageClass


@dataclass(frozen=True, slots=True)
class NeedsCommit:
    """Steps 1-6 passed: the driver commits the msg_id, then calls :meth:`Steps.accept`."""

    env: Envelope
    signer: Signer
    cls: MessageClass

    def refused(self, error: ReplayAttackError) -> Done:
        """The commit refused the message (a racer won, a fence, the store down)."""
        return Done(error, self.env, self.signer, self.cls[0])


@dataclass(frozen=True, slots=True)
class Done:
    """A refusal decided before or at the commit, with what was known of the message."""

    error: ReplayAttackError
    env: Envelope | None = None
    signer: Signer | None = None
    msg_type: int | None = None


@dataclass(frozen=True, slots=True)
class Accepted:
    """An admitted message: its outcome, the answer entry its QoS retries will look up,
    and whether its body may enter the known-copy memo (no warning, not an ESTOP)."""

    outcome: Outcome
    entry: Entry | None
    memo: bool
    qos: bool


class Steps:
    """The §8.3 steps for one robot's configuration (see the module docstring)."""

    def __init__(
        self,
        config: SecurityConfig,
        keys: KeyRegistry,
        *,
        jwt: JwtVerifier | None,
        jwt_required: bool,
        versions: frozenset[str],
        max_bytes: int,
    ) -> None:
        self.config = config
        self.keys = keys
        self.jwt = jwt
        self.jwt_required = jwt_required
        self.versions = versions
        self.max_bytes = max_bytes

    def parse(self, raw: bytes) -> Checked | Done:
        """Steps 1-2: the envelope and its class, or why it is refused."""
        env: Envelope | None = None
        cls: MessageClass | None = None
        try:
            env = parse(raw, max_bytes=self.max_bytes)
            cls = safety_class(env)
            self._check_version(env)
        except ReplayAttackError as exc:
            return Done(exc, env, None, None if cls is None else cls[0])
        return Checked(env, cls)

    def authenticate(
        self,
        checked: Checked,
        replayed: ReplayAttackError | None,
        headers: Mapping[str, str] | None,
    ) -> NeedsCommit | Done:
        """Steps 4-6 after the replay check refused (``replayed``) or passed the message."""
        env = checked.env
        signer: Signer | None = None
        try:
            if replayed is not None:
                if may_retry(replayed, env):  # its answer has content: only after the token
                    self._check_jwt(env, headers or {})
                raise replayed
            self._check_jwt(env, headers or {})
            signer = self.keys.verify(env)
            self._authorize(env, signer, checked.cls[0])
        except ReplayAttackError as exc:
            return Done(exc, env, signer, checked.cls[0])
        return NeedsCommit(env, signer, checked.cls)

    def accept(self, need: NeedsCommit, verdict: Verdict) -> Accepted:
        """Step 7 admitted the message: its outcome (unsigned delivery hints removed)."""
        env, signer = need.env, need.signer
        memo = verdict.warning is None and not verdict.estop
        qos = env.qos >= 1  # declared (an SDK signer's is stripped below)
        entry: Entry | None = None
        if memo and qos:  # its retransmissions get the answer the transport holds
            found = digest(env, signer.subset)
            if found is not None:
                entry = Entry(found, signer.subset, verdict.expires_at, signer)
        if signer.subset:
            env = without_delivery_hints(env)  # unsigned: never forwarded
        outcome = Outcome(
            True, 200, warning=verdict.warning, msg_id=sanitize(env.msg_id), envelope=env,
            signer=signer, msg_type=need.cls[0],
        )  # fmt: skip
        return Accepted(outcome, entry, memo, qos)

    def refuse(self, done: Done, msg_id: str | None = None) -> Outcome:
        """The NACK outcome of a refusal (``msg_id``: a known copy's, nothing parsed)."""
        exc, env = done.error, done.env
        return Outcome(
            False, exc.http_status, str(exc.code), exc.reason,
            msg_id=msg_id if env is None else sanitize(env.msg_id), envelope=env,
            signer=done.signer, error=exc, nack_type=self.config.nack_type,
            msg_type=done.msg_type,
        )  # fmt: skip

    def _check_version(self, env: Envelope) -> None:
        version = env.rcan_version or env.rcan
        if not version:
            raise VersionIncompatibleError("no rcan_version")
        if version.split(".", 1)[0] not in self.versions:
            raise VersionIncompatibleError(
                f"RCAN major version not supported (speaks {sorted(self.versions)})"
            )

    def _check_jwt(self, env: Envelope, headers: Mapping[str, str]) -> None:
        token = _bearer(headers) or env.jwt
        if token is None:
            if self.jwt_required:
                raise AuthFailedError("bearer token required")
            return
        if self.jwt is None:
            raise AuthFailedError("bearer tokens are not accepted here")
        _, entry = self.keys.signing_key(env)  # unsigned or unknown key: its own code
        self.jwt.check(token, entry.owner)

    def _authorize(self, env: Envelope, signer: Signer, msg_type: int) -> None:
        if signer.subset:
            unsigned = unsigned_policy_fields(env)
            if unsigned:
                raise ScopeDeniedError(
                    f"fields not covered by the RCAN SDK signature: {', '.join(unsigned)}"
                )
        needed = "safety" if msg_type == MessageType.SAFETY else (env.scope or "control")
        if needed not in signer.scopes and "*" not in signer.scopes:
            raise ScopeDeniedError(f"key {sanitize(signer.kid)} lacks scope {sanitize(needed)}")


def audit_row(outcome: Outcome, at: float, sender: str | None = None) -> AuditRow:
    """The audit row of an outcome (``sender``: a known copy's claimed sender).  Unverified,
    the sender is what the message claims: its ``sender`` field, else its key id
    (``kid:NAME``; a replay is refused before its signature is checked)."""
    return AuditRow(
        at=at,
        outcome="accepted" if outcome.accepted else "rejected",
        code=outcome.code,
        warning=outcome.warning or (outcome.error.detail if outcome.error else None),
        msg_type=outcome.msg_type,
        sender=row_sender(outcome, sender),
        sender_verified=outcome.signer is not None,
        msg_id=outcome.msg_id,
    )


def row_sender(outcome: Outcome, sender: str | None = None) -> str | None:
    """The sender an outcome's row names (see :func:`audit_row`): the refusal auditor
    decides on it before any row is built."""
    signer, env = outcome.signer, outcome.envelope
    if signer is not None:
        return signer.owner
    if env is not None:
        return env.sender or claimed_kid(env)
    return sender


def accepted_row(need: NeedsCommit, at: float, warning: str | None = None) -> AuditRow:
    """The row :func:`audit_row` writes for ``need``'s acceptance (:meth:`Steps.accept`'s
    outcome), built before its commit: the commit's writer puts it with the entry."""
    return AuditRow(
        at=at, outcome="accepted", warning=warning, msg_type=need.cls[0],
        sender=need.signer.owner, sender_verified=True, msg_id=sanitize(need.env.msg_id),
    )  # fmt: skip


def claimed_kid(env: Envelope) -> str | None:
    """``kid:NAME`` of the signature block ``env`` carries (unverified), or ``None``."""
    try:
        sig = env.signature()
    except ReplayAttackError:
        return None
    return None if sig is None else f"kid:{sig.kid}"


def may_retry(error: ReplayAttackError, env: Envelope) -> bool:
    """Whether the retry rule decides this refusal: ``REPLAY_DETECTED`` for a message that
    declares ``qos`` >= 1 (answered with the original answer if its content matches)."""
    return error.code == Code.REPLAY_DETECTED and env.qos >= 1


def _bearer(headers: Mapping[str, str]) -> str | None:
    for name, value in headers.items():
        if name.lower() == "authorization" and value.startswith("Bearer "):
            return value[len("Bearer ") :].strip() or None
    return None
