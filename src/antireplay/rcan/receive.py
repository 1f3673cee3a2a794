"""The receive path: RCAN §8.3's check order, check -> authenticate -> commit, NACKs and audit.

Theory of operation
-------------------
:meth:`Receiver.receive` runs the steps cheapest first, so a replay is thrown
away before any cryptography:

0. a byte-identical copy of a message accepted here     -> REPLAY_DETECTED 409
   (a bounded memo of accepted bodies, no parse, no
   I/O; :meth:`Receiver.reject_known_copy`).  ESTOPs and
   messages accepted with a warning never enter it, so
   a fresh duplicate ESTOP still takes steps 1-7 and
   keeps its exemption; a forgotten copy takes the full
   path and is refused at step 3, and so does a copy of
   a message that declared ``qos`` >= 1 (its retry is
   decided there)
1. parse the envelope (size, depth, schema)              -> INVALID_ENVELOPE 400
2. check the RCAN version                                -> VERSION_INCOMPATIBLE 426
3. replay check: freshness + msg_id seen-set, the       -> MESSAGE_STALE 408 /
   store's fence and watermark                              REPLAY_DETECTED 409
   (:meth:`ReplayCache.check`, records nothing);            or the original answer
   REPLAY_DETECTED for a QoS retransmission: the            (``Outcome.retry``)
   retry rule below, after step 4 (its answer has
   content), no signature check
4. JWT, if configured or presented (an unsigned or      -> AUTH_FAILED 401
   unknown-key envelope gets its own code, as at 5)
5. signature over the canonical envelope                 -> SIGNATURE_REQUIRED /
                                                            UNKNOWN_SENDER /
                                                            SIGNATURE_INVALID 401
6. authorization (scopes; SDK-compat field rule)         -> SCOPE_DENIED 403
7. **commit**: the store's atomic record of the msg_id   -> REPLAY_DETECTED 409
   (:meth:`ReplayCache.commit`; two copies racing         MESSAGE_STALE 408
   through crypto: exactly one wins; a store that lost   (fence, watermark)
   state is noticed here, atomically)

Nothing an unauthenticated packet carries changes replay state: the msg_id is
recorded only at step 7.  So a forged message carrying a victim's msg_id is
rejected at step 5 and the genuine message is still accepted afterwards.

ESTOP invariant, end to end: a fresh, *authentic* SAFETY/ESTOP whose msg_id
was already seen passes with ``warning="REPLAY_DETECTED"``; the warning is
audited.  The same ESTOP is delivered whatever the state and the audit trail
can do (one rule, here): the replay store unreachable at step 7
(``warning="STATE_UNAVAILABLE"``, :class:`~antireplay.state.replay.ReplayCache`), and its
audit row not durable at :meth:`~Receiver.settle` (``warning="AUDIT_UNAVAILABLE"``
unless the ESTOP already carries one: one stable code per answer, the §8.3 flag
first).  Such a row is held in memory (bounded, :data:`HELD_ROWS`; an overflow is
counted and logged), said once on the log per outage, counted
(``stats.held_estops``), and appended to the trail by the next answer whose own row
was durable.  What is SAFETY/ESTOP is decided by
:func:`~antireplay.rcan.envelope.safety_class` from signed fields only: ``type`` and
``safety_event`` (covered by a full signature), or ``cmd`` ``ESTOP``/``STOP``/
``RESUME`` (covered by the RCAN SDK's signature too, whose unsigned ``type`` and
``safety_event`` are refused at step 6).  So nobody can turn a captured command
into an exempt ESTOP.  An SDK-signed message's unsigned ``qos`` hint is removed
from the accepted envelope (nothing unsigned is forwarded).

QoS retries (:mod:`antireplay.rcan.answers`).  A message that declares ``qos`` >= 1
and is refused ``REPLAY_DETECTED`` (step 3, or step 7 when two copies raced) is a
*retransmission* when a digest of its authenticated content (signed bytes,
signature alg, kid and value) equals the one kept for its msg_id when that
message was accepted here: the same bytes under the same signature as a message
verified here, so no second signature check; but the bearer token (step 4) is checked
first, as for an original: without a valid one the retry gets the original's refusal,
``AUTH_FAILED``, never the held answer.  It is answered with the original
answer (:attr:`Outcome.retry`: same status and body, ``"duplicate": true``, header
``rcan-duplicate: true``), audited as ``REPLAY_DETECTED`` with warning
``QOS_RETRY`` under the original's verified sender, counted (``stats.retries``),
and never executed or forwarded again.  The transport hands every accepted
outcome's answer to :meth:`Receiver.hold_answer` (also an upstream failure's NACK,
audited by :meth:`Receiver.record_upstream_failure`);
until then the original is *in flight*: :meth:`Receiver.receive_async` waits for it
on the loop (at most ``answer_wait_s``, no thread held), :meth:`Receiver.receive`
refuses at once.  No qos, other content, no held answer (evicted, too large,
restarted, another replica, none in time): ``REPLAY_DETECTED`` 409 as before.  An
ESTOP is never held: its fresh duplicate is processed (the invariant above).

Every rejection becomes an :class:`Outcome` carrying the code, the HTTP status
and the COMMAND_NACK (type 18, or 31 with ``nack_type: 31``); nothing raises out
of ``receive``.  The audit trail always gets accepted messages and every
rejection from step 2 on; malformed input (step 1 and bad msg_id/timestamp
shapes) is audited at most ``invalid_audit_per_s`` times a second so a flood of
garbage cannot turn into a flood of fsyncs (it is still counted in ``stats``).

No answer goes out before its audit row is durable.  :meth:`Receiver.receive`
is :meth:`~Receiver.receive_later` (every step, the audit row *queued* for the
trail's next group commit) followed by :meth:`~Receiver.settle` once that row
is durable; :meth:`~Receiver.receive_async` runs the two halves on an event loop
and awaits the row in between without holding a thread.  An accepted message
whose row cannot be made durable is refused (``STATE_UNAVAILABLE``) at ``settle``,
except a fresh, authentic ESTOP (above).
"""

from __future__ import annotations

import asyncio
import functools
import logging
import threading
from collections import Counter, deque
from collections.abc import Awaitable, Callable, Iterable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

from antireplay.audit import AuditLog, RefusalAuditor, sanitize
from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import (
    AuthFailedError,
    Code,
    ReplayAttackError,
    ReplayDetectedError,
    ScopeDeniedError,
    StateUnavailableError,
    VersionIncompatibleError,
    WarningCode,
    command_ack,
)
from antireplay.core.messages import MessageType
from antireplay.core.settings import SecurityConfig
from antireplay.core.window import Seen, Verdict
from antireplay.rcan.answers import QOS_RETRY, AnswerMemo, Entry, HeldAnswer, digest
from antireplay.rcan.auth import JwtVerifier, KeyRegistry, Signer
from antireplay.rcan.envelope import (
    MAX_BYTES,
    Envelope,
    parse,
    safety_class,
    unsigned_policy_fields,
    without_delivery_hints,
)
from antireplay.state import ReplayStore
from antireplay.state.replay import ReplayCache

SHAPE_ERRORS = frozenset({Code.INVALID_ENVELOPE, Code.INVALID_MESSAGE_ID, Code.INVALID_TIMESTAMP})
#: Audit rows of ESTOPs delivered while the trail could not take them, held until it can.
HELD_ROWS = 1024

log = logging.getLogger("antireplay.rcan.receive")


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


@dataclass(slots=True)
class Pending:
    """An outcome whose audit row may not be durable yet; :meth:`Receiver.settle` answers."""

    outcome: Outcome
    #: The queued audit row (``None``: nothing to wait for: no trail, or not audited);
    #: an asyncio future when an event loop queued it (:meth:`Receiver.reject_known_copy`).
    audit: Future[int] | asyncio.Future[int] | None = None
    #: An accepted body, its expiry and whether it declared ``qos`` >= 1, remembered as a
    #: known copy once audited.
    memo: tuple[bytes, float, bool] | None = None
    #: A fresh, authentic ESTOP: delivered even when its audit row cannot be made durable.
    estop: bool = False
    #: The audit row queued (kept to be held and appended later if it fails).
    row: dict[str, Any] | None = None


#: Runs ``fn(*args)`` in a thread; the event loop awaits the result.
Offload = Callable[..., Awaitable[Any]]


def _default_offload(fn: Callable[..., Any], *args: Any) -> Awaitable[Any]:
    return asyncio.get_running_loop().run_in_executor(None, fn, *args)


def _wait(audit: Future[int] | asyncio.Future[int] | None) -> BaseException | None:
    """Block until the audit row is durable: ``None``, or why it could not be made so."""
    if audit is None:
        return None
    assert isinstance(audit, Future), "a row queued by an event loop is awaited there"
    try:
        audit.result()
    except Exception as exc:  # any failure to record is the answer
        return exc
    return None


@dataclass(frozen=True, slots=True)
class _Copy:
    """What is remembered of an accepted body (never the body itself)."""

    length: int
    expires_at: float
    msg_id: str | None
    type: int  # the type the policy applied (envelope.safety_class)
    sender: str | None
    qos: bool  # declared qos >= 1: a copy goes on to step 3, where its retry is decided


@dataclass
class Stats:
    """Counters for metrics: accepted, rejected by code, warnings, unaudited shape errors."""

    accepted: int = 0
    rejected: Counter[str] = field(default_factory=Counter)
    warnings: Counter[str] = field(default_factory=Counter)
    unaudited: int = 0
    audit_failures: int = 0
    losses: int = 0
    #: QoS retransmissions answered with their original answer (also in ``rejected``).
    retries: int = 0
    #: ESTOPs delivered while their audit row could not be written (held, appended later).
    held_estops: int = 0
    #: Held rows dropped unwritten because the bound was reached (each one logged).
    held_dropped: int = 0


class Receiver:
    """One robot's receive path; thread-safe (the window and stores are atomic)."""

    def __init__(
        self,
        config: SecurityConfig,
        keys: KeyRegistry,
        store: ReplayStore | None = None,
        audit: AuditLog | None = None,
        clock: Clock | None = None,
        *,
        jwt: JwtVerifier | None = None,
        jwt_required: bool = False,
        versions: frozenset[str] = frozenset({"3"}),
        invalid_audit_per_s: float = 10.0,
        max_bytes: int = MAX_BYTES,
    ) -> None:
        self.config = config
        self.max_bytes = max_bytes  # the gateway passes its max_body_bytes: one limit in force
        self.keys = keys
        self.audit = audit
        self.clock = resolve(clock)
        self.cache = ReplayCache.from_config(config, self.clock, store)
        self.cache.on_loss = self._audit_loss
        self.jwt = jwt
        self.jwt_required = jwt_required
        self.versions = versions
        self.stats = Stats()
        self._copies: dict[int, _Copy] = {}
        self.answers = AnswerMemo(config.msg_id_cache_size)
        #: How long an event loop waits for the answer of an original still in flight.
        self.answer_wait_s = 5.0
        self._refusals = RefusalAuditor(clock=self.clock, per_s=invalid_audit_per_s)
        self._held: deque[dict[str, Any]] = deque()
        self._held_lock = threading.Lock()
        reason = getattr(self.cache.store, "loss_reason", None)
        if reason is not None:  # noticed while the store opened (a lost or rolled-back file)
            self._audit_loss(str(reason))

    def receive(self, raw: bytes, headers: Mapping[str, str] | None = None) -> Outcome:
        """Run the §8.3 steps; never raises for anything a peer can send."""
        pending = self.receive_later(raw, headers)
        return self.settle(pending, _wait(pending.audit))

    def receive_later(self, raw: bytes, headers: Mapping[str, str] | None = None) -> Pending:
        """Every step through the commit; the outcome's audit row is queued for the next
        group commit, not awaited.  Answer with :meth:`settle` once ``Pending.audit`` is
        done (:meth:`receive` blocks on it)."""
        copy = self._known_copy(raw)
        if copy is not None:
            return self._reject_copy(copy)
        env, signer, error = self._authenticate(raw, headers)
        if error is None:
            assert env is not None and signer is not None
            try:
                verdict = self.cache.commit(env.msg_id, env.seconds, *safety_class(env))
            except ReplayAttackError as exc:
                error = exc
            else:
                return self._accept(raw, env, signer, verdict)
        entry, error = self._retry_entry(error, env)
        if entry is not None and entry.answer is not None:
            return self._answer_retry(entry, entry.answer, env)
        if entry is not None:  # in flight: only an event loop waits (receive_async)
            error = _not_held("original answer not held here yet (still in flight)")
        return self._reject(error, env, signer)

    async def receive_async(
        self, raw: bytes, headers: Mapping[str, str] | None = None, offload: Offload | None = None
    ) -> Outcome:
        """:meth:`receive` for an event loop: the settled outcome, its audit row durable,
        awaited without holding a thread (:meth:`receive_later_async`, then :meth:`settle`)."""
        pending = await self.receive_later_async(raw, headers, offload)
        failure: BaseException | None = None
        audit = pending.audit
        if audit is not None:
            try:
                await (audit if isinstance(audit, asyncio.Future) else asyncio.wrap_future(audit))
            except Exception as exc:  # settle() turns any failure into the answer
                failure = exc
        if failure is not None and pending.outcome.accepted:  # its refusal is audited: blocks
            outcome: Outcome = await (offload or _default_offload)(self.settle, pending, failure)
            return outcome
        return self.settle(pending, failure)

    async def receive_later_async(
        self, raw: bytes, headers: Mapping[str, str] | None = None, offload: Offload | None = None
    ) -> Pending:
        """:meth:`receive_later` for an event loop, holding a thread only while there is work
        for one: a byte-identical copy is refused on the loop; parsing, the pre-crypto check
        (a store read) and the signature run in a thread (``offload(fn, *args)``, default
        the loop's executor); a group-committing store's commit (``commit_async``) and
        every audit row are awaited on the loop."""
        pending = self.reject_known_copy(raw)
        if pending is not None:
            return pending
        run = offload or _default_offload
        env, signer, error = await run(self._authenticate, raw, headers)
        if error is not None:
            return await self._reject_async(error, env, signer)
        assert env is not None and signer is not None
        cache = self.cache
        try:
            plan, now = cache.begin_commit(env.msg_id, env.seconds, *safety_class(env))
            args = (plan.msg_id, plan.expires_at, now, plan.estop)
            seen: Seen | StateUnavailableError
            try:
                commit_async = getattr(cache.store, "commit_async", None)
                if commit_async is not None:
                    seen = await commit_async(*args)
                else:
                    seen = await run(cache.store.commit, *args)
            except StateUnavailableError as exc:
                seen = exc
            verdict = cache.finish_commit(plan, now, seen)
        except ReplayAttackError as exc:
            return await self._reject_async(exc, env, signer)
        return self._accept(raw, env, signer, verdict, on_loop=True)

    async def _reject_async(
        self, error: ReplayAttackError, env: Envelope | None, signer: Signer | None
    ) -> Pending:
        """The refusal, or a QoS retransmission's original answer, awaited on the loop
        while the original is still in flight (at most ``answer_wait_s``)."""
        entry, error = self._retry_entry(error, env)
        if entry is not None:
            held = await self.answers.wait(entry, self.answer_wait_s)
            if held is not None:
                return self._answer_retry(entry, held, env, on_loop=True)
            error = _not_held("original answer not held here (none arrived in time)")
        return self._reject(error, env, signer, on_loop=True)

    def _retry_entry(
        self, error: ReplayAttackError, env: Envelope | None
    ) -> tuple[Entry | None, ReplayAttackError]:
        """For a ``REPLAY_DETECTED`` message that declares ``qos`` >= 1 and carries the
        same authenticated content as the message accepted under its msg_id: that
        message's answer entry (held or in flight; no signature check, answers.py).
        Otherwise ``None`` and the refusal to send."""
        if env is None or not _may_retry(error, env):
            return None, error
        entry = self.answers.find(env, self.clock.wall())
        return entry, error if entry is not None else _not_held("original answer not held here")

    def hold_answer(
        self,
        outcome: Outcome,
        status: int,
        headers: Iterable[tuple[str, str]],
        body: bytes,
    ) -> None:
        """Keep the answer a transport produced for an accepted message (also an upstream
        failure's), for its QoS retransmissions; call it before sending the answer.  A
        no-op unless the message declared ``qos`` >= 1 (answers.py bounds what is kept)."""
        env = outcome.envelope
        if outcome.accepted and env is not None and type(env.msg_id) is str:
            self.answers.hold(env.msg_id, status, headers, body)

    async def record_upstream_failure(self, outcome: Outcome, error: ReplayAttackError) -> None:
        """Audit that an accepted message's upstream failed (``UPSTREAM_FAILED``, warning
        ``delivered=…``, under its verified sender), queued with the other rows and durable
        before the failure is answered; a row that cannot be written is counted."""
        failed = Outcome(
            False, error.http_status, str(error.code), error.reason, msg_id=outcome.msg_id,
            envelope=outcome.envelope, signer=outcome.signer, error=error,
            nack_type=self.config.nack_type,
        )  # fmt: skip
        audit = self._queue_audit(Pending(failed), on_loop=True).audit
        if audit is None:
            return
        try:
            await (audit if isinstance(audit, asyncio.Future) else asyncio.wrap_future(audit))
        except Exception:  # the failure is still answered; the missing row is counted
            self.stats.audit_failures += 1

    def _answer_retry(
        self, entry: Entry, held: HeldAnswer, env: Envelope | None, *, on_loop: bool = False
    ) -> Pending:
        """A QoS retransmission: the original answer, audited as a refused replay
        (``REPLAY_DETECTED``, warning ``QOS_RETRY``) by the original's verified signer."""
        exc = ReplayDetectedError(
            "QoS retransmission: the original answer, not executed again", detail=QOS_RETRY
        )
        outcome = self._outcome(exc, env, entry.signer, None)
        outcome.retry = held  # status, nack: still 409, what a retry-unaware transport sends
        self.stats.rejected[exc.code] += 1
        self.stats.retries += 1
        return self._queue_audit(Pending(outcome), on_loop=on_loop)

    def _authenticate(
        self, raw: bytes, headers: Mapping[str, str] | None
    ) -> tuple[Envelope | None, Signer | None, ReplayAttackError | None]:
        """Steps 1-6: parse, version, the replay check (records nothing), JWT, signature,
        scopes.  The envelope and signer found so far, and the refusal if any."""
        env: Envelope | None = None
        signer: Signer | None = None
        try:
            env = parse(raw, max_bytes=self.max_bytes)
            self._check_version(env)
            msg_type, event = safety_class(env)
            try:
                self.cache.check(env.msg_id, env.seconds, msg_type, event)
            except ReplayAttackError as exc:
                if _may_retry(exc, env):  # its answer has content: only after the token
                    self._check_jwt(env, headers or {})
                raise
            self._check_jwt(env, headers or {})
            signer = self.keys.verify(env)
            self._authorize(env, signer, msg_type)
        except ReplayAttackError as exc:
            return env, signer, exc
        return env, signer, None

    def _accept(
        self, raw: bytes, env: Envelope, signer: Signer, verdict: Verdict, *, on_loop: bool = False
    ) -> Pending:
        memo = verdict.warning is None and not verdict.estop
        qos = env.qos >= 1  # declared (an SDK signer's is stripped below)
        if memo and qos:  # its retransmissions get the answer the transport holds
            found = digest(env, signer.subset)
            if found is not None:
                entry = Entry(found, signer.subset, verdict.expires_at, signer)
                self.answers.expect(env.msg_id, entry, self.clock.wall())
        if signer.subset:
            env = without_delivery_hints(env)  # unsigned: never forwarded
        outcome = Outcome(
            True, 200, warning=verdict.warning, msg_id=sanitize(env.msg_id), envelope=env,
            signer=signer,
        )  # fmt: skip
        pending = Pending(
            outcome, memo=(raw, verdict.expires_at, qos) if memo else None, estop=verdict.estop
        )
        return self._queue_audit(pending, on_loop=on_loop)

    def settle(self, pending: Pending, failure: BaseException | None) -> Outcome:
        """The answer, once the outcome's audit row is durable (``failure`` is ``None``) or
        could not be made durable.  Only an accepted message whose row failed blocks (its
        refusal is audited in turn): run that case off the event loop."""
        outcome = pending.outcome
        if failure is not None:
            self.stats.audit_failures += 1
            if outcome.accepted and pending.estop:  # safety beats the audit trail
                self._hold(pending, failure)
            elif outcome.accepted:
                # Nothing accepted may be missing from the audit trail: refuse to act on it.
                # Its msg_id is spent; the sender resends with a new one once the disk is back.
                if outcome.envelope is not None and type(outcome.envelope.msg_id) is str:
                    self.answers.drop(outcome.envelope.msg_id)  # no answer to hold
                exc = StateUnavailableError(f"audit trail unavailable: {failure}")
                refusal = self._reject(exc, outcome.envelope, outcome.signer)
                return self.settle(refusal, _wait(refusal.audit))
            else:
                return outcome  # the rejection stands; it could not be recorded
        elif pending.audit is not None:
            self._append_held()  # the trail took a row: it can take the held ones
        if outcome.accepted:
            self.stats.accepted += 1
            if outcome.warning:
                self.stats.warnings[outcome.warning] += 1
            elif pending.memo is not None and outcome.envelope is not None:
                self._remember_copy(*pending.memo, outcome.envelope)
        return outcome

    @property
    def held_rows(self) -> int:
        """Audit rows of delivered ESTOPs waiting for the trail to be writable."""
        return len(self._held)

    def _hold(self, pending: Pending, failure: BaseException) -> None:
        """Deliver an ESTOP whose audit row failed: warn, keep the row for later, say so once."""
        outcome = pending.outcome
        if outcome.warning is None:
            outcome.warning = WarningCode.AUDIT_UNAVAILABLE
        self.stats.held_estops += 1
        if pending.row is None:
            return
        if self._keep({**pending.row, "warning": outcome.warning}):
            log.error(
                "audit trail unavailable (%s): ESTOPs are delivered with a warning and their "
                "audit rows held in memory until the trail takes a row again; other messages "
                "get STATE_UNAVAILABLE",
                failure,
            )

    def _append_held(self) -> None:
        """After a row was made durable, queue the held ESTOP rows; one that fails again is
        held again (its ``at`` keeps when it happened)."""
        if not self._held or self.audit is None:
            return
        with self._held_lock:
            rows = list(self._held)
            self._held.clear()
        log.warning("audit trail writable again: appending %d held ESTOP rows", len(rows))
        for row in rows:
            try:
                future = self.audit.append_later(**row)
            except RuntimeError:  # closing: nothing more will be written
                self._keep(row)
                continue
            assert isinstance(future, Future)
            future.add_done_callback(functools.partial(self._held_written, row))

    def _held_written(self, row: dict[str, Any], done: Future[int]) -> None:
        if done.exception() is not None:
            self._keep(row)

    def _keep(self, row: dict[str, Any]) -> bool:
        """Hold one row (the oldest dropped beyond :data:`HELD_ROWS`, its log line then its
        only record); ``True`` if none was held before."""
        with self._held_lock:
            first = not self._held
            if len(self._held) >= HELD_ROWS:
                dropped = self._held.popleft()
                self.stats.held_dropped += 1
                log.error("held audit row dropped (more than %d held): %s", HELD_ROWS, dropped)
            self._held.append(row)
        return first

    def _remember_copy(self, raw: bytes, expires_at: float, qos: bool, env: Envelope) -> None:
        """Memo of accepted bodies: a byte-identical copy is a replay, known before parsing.

        Only authenticated, accepted, non-ESTOP messages enter it (a fresh duplicate ESTOP
        must still be processed), keyed by Python's keyed SipHash of the body plus its
        length; it is bounded (oldest forgotten first) and forgetting only means the copy
        takes the full path, where the window rejects it as before.  A copy of a message
        that declared ``qos`` >= 1 is not refused here: it goes on to step 3, where the
        retry rule is decided (one decision point; a parse, no crypto).
        """
        copies = self._copies
        if len(copies) >= self.config.msg_id_cache_size:
            copies.pop(next(iter(copies)), None)
        msg_type = safety_class(env)[0]
        copies[hash(raw)] = _Copy(
            len(raw), expires_at, sanitize(env.msg_id), msg_type, env.sender, qos
        )

    def _known_copy(self, raw: bytes) -> _Copy | None:
        copy = self._copies.get(hash(raw)) if type(raw) is bytes else None
        if copy is not None and copy.length == len(raw) and copy.expires_at >= self.clock.wall():
            return None if copy.qos else copy
        return None

    def _reject_copy(self, copy: _Copy) -> Pending:
        exc = ReplayDetectedError("an identical message was already accepted")
        return self._reject(exc, None, None, copy=copy)

    def reject_known_copy(self, raw: bytes) -> Pending | None:
        """Step 0 without blocking: a byte-identical copy of an accepted message is refused
        with no parsing, no lock and no I/O; its audit row is queued for the next group
        commit (answer with :meth:`settle` once ``Pending.audit`` is done).  ``None``: not
        a known copy, run :meth:`receive_later`."""
        copy = self._known_copy(raw)
        if copy is None:
            return None
        exc = ReplayDetectedError("an identical message was already accepted")
        return self._reject(exc, None, None, copy=copy, on_loop=True)

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

    def _reject(
        self,
        exc: ReplayAttackError,
        env: Envelope | None,
        signer: Signer | None,
        *,
        copy: _Copy | None = None,
        on_loop: bool = False,
    ) -> Pending:
        """The NACK outcome for ``exc``; ``copy`` describes a memo hit (no envelope parsed)."""
        outcome = self._outcome(exc, env, signer, copy)
        self.stats.rejected[exc.code] += 1
        if exc.code in SHAPE_ERRORS and not self._refusals.admit(authentic=False):
            self.stats.unaudited += 1
            return Pending(outcome)
        return self._queue_audit(Pending(outcome), copy, on_loop=on_loop)

    def _outcome(
        self,
        exc: ReplayAttackError,
        env: Envelope | None,
        signer: Signer | None,
        copy: _Copy | None,
    ) -> Outcome:
        msg_id = copy.msg_id if copy is not None else sanitize(env.msg_id) if env else None
        return Outcome(
            False,
            exc.http_status,
            str(exc.code),
            exc.reason,
            msg_id=msg_id,
            envelope=env,
            signer=signer,
            error=exc,
            nack_type=self.config.nack_type,
        )

    def _audit_loss(self, reason: str) -> None:
        """A store noticed it may have forgotten accepted messages: fenced, and on the record."""
        self.stats.losses += 1
        if self.audit is None:
            return
        try:
            self.audit.append(
                at=self.clock.wall(), outcome="state", code=WarningCode.STATE_LOST,
                warning=reason[:200], msg_type=None, sender=None, sender_verified=False,
                msg_id=None,
            )  # fmt: skip
        except StateUnavailableError:
            self.stats.audit_failures += 1

    def _queue_audit(
        self, pending: Pending, copy: _Copy | None = None, *, on_loop: bool = False
    ) -> Pending:
        """Queue the outcome's audit row (``on_loop``: awaited by the running event loop);
        a trail that is closing fails the row at once."""
        if self.audit is not None:
            outcome = pending.outcome
            fields = self._audit_fields(outcome, outcome.envelope, outcome.signer, copy)
            if pending.estop:
                pending.row = fields
            try:
                pending.audit = self.audit.append_later(**fields, on_loop=on_loop)
            except RuntimeError as exc:
                failed: Future[int] = Future()
                failed.set_exception(exc)
                pending.audit = failed
        return pending

    def _audit_fields(
        self,
        outcome: Outcome,
        env: Envelope | None,
        signer: Signer | None,
        copy: _Copy | None,
    ) -> dict[str, Any]:
        source = copy if copy is not None else env  # both carry ``sender``
        msg_type = copy.type if copy is not None else safety_class(env)[0] if env else None
        return {
            "at": self.clock.wall(),
            "outcome": "accepted" if outcome.accepted else "rejected",
            "code": outcome.code,
            "warning": outcome.warning or (outcome.error.detail if outcome.error else None),
            "msg_type": msg_type,
            "sender": signer.owner if signer else source.sender if source is not None else None,
            "sender_verified": signer is not None,
            "msg_id": outcome.msg_id,
        }


def _may_retry(error: ReplayAttackError, env: Envelope) -> bool:
    """Whether the retry rule decides this refusal: ``REPLAY_DETECTED`` for a message that
    declares ``qos`` >= 1 (answered with the original answer if its content matches)."""
    return error.code == Code.REPLAY_DETECTED and env.qos >= 1


def _not_held(why: str) -> ReplayDetectedError:
    return ReplayDetectedError(f"msg_id already accepted; {why}")


def _bearer(headers: Mapping[str, str]) -> str | None:
    for name, value in headers.items():
        if name.lower() == "authorization" and value.startswith("Bearer "):
            return value[len("Bearer ") :].strip() or None
    return None
