"""What the RCAN receive drivers share: the receiver's state and every rule between the
core's calls, written once.

Theory of operation
-------------------
:class:`ReceiverBase` holds one robot's receive state: the replay window
(:class:`~antireplay.state.replay.ReplayCache`), the sans-I/O core
(:class:`~antireplay.rcan.steps.Steps`), the memo of accepted bodies, the QoS answers,
the refusal auditor and the counters.  Its methods decide; they queue nothing: an
outcome leaves as a :class:`Pending` carrying its audit ``row`` (``None``: no row: no
trail, or folded into the auditor's summary), and the driver that asked queues the row
its own way: :mod:`~antireplay.rcan.receive` on a thread, :mod:`~antireplay.rcan.receive_loop`
on an event loop (:func:`queue_row`, the one place a row meets the trail).

Step 0, before any parse: a byte-identical copy of a message accepted here is refused
``REPLAY_DETECTED`` from a bounded memo (no I/O); ESTOPs, warned messages and ``qos``
>= 1 ones never enter it.  A ``REPLAY_DETECTED`` message with ``qos`` >= 1 whose
authenticated content matches the accepted one is a QoS retransmission: answered with
the original's held answer (:mod:`~antireplay.rcan.answers`, :attr:`Outcome.retry`),
never executed again.  Below the disk's second floor (:mod:`~antireplay.audit.space`)
all but a fresh ESTOP is refused ``STATE_UNAVAILABLE`` before its commit.

No answer goes out before its audit row is durable (:meth:`ReceiverBase.settle`).  An
accepted message whose row failed is refused ``STATE_UNAVAILABLE``, except a fresh,
authentic ESTOP (:func:`~antireplay.core.window.estop_survives`): delivered flagged
``AUDIT_UNAVAILABLE``, its row spilled to the trail's reserved file
(:mod:`~antireplay.audit.spill`), merged into the trail later.  Nothing raises.

Size: one idea, the rules between the core's calls that both drivers run (the paired
one-trip commit included); splitting it would make each driver carry half of them.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from typing import cast

from antireplay.audit import AuditLog, AuditRow, RefusalAuditor
from antireplay.audit.refusals import AUDIT_PER_S
from antireplay.audit.space import DiskSpace
from antireplay.audit.spill import SLOTS as HELD_ROWS  # ESTOP rows held for the trail
from antireplay.audit.writer import stored_json
from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import (
    Code,
    ReplayAttackError,
    ReplayDetectedError,
    StateUnavailableError,
    WarningCode,
)
from antireplay.core.settings import SecurityConfig
from antireplay.core.window import Refusal, Seen, Verdict, estop_survives, is_estop
from antireplay.rcan.answers import QOS_RETRY, AnswerMemo, Entry, HeldAnswer
from antireplay.rcan.auth import JwtVerifier, KeyRegistry
from antireplay.rcan.envelope import MAX_BYTES
from antireplay.rcan.steps import (
    Checked,
    Done,
    NeedsCommit,
    Outcome,
    Steps,
    accepted_row,
    audit_row,
    may_retry,
    row_sender,
)  # fmt: skip
from antireplay.state import ReplayStore
from antireplay.state.replay import ReplayCache
from antireplay.state.sqlite import SAFETY_WAIT_S, SqliteStore

SHAPE_ERRORS = frozenset({Code.INVALID_ENVELOPE, Code.INVALID_MESSAGE_ID, Code.INVALID_TIMESTAMP})

log = logging.getLogger("antireplay.rcan.receive")

__all__ = ["HELD_ROWS", "SHAPE_ERRORS", "Pending", "ReceiverBase", "Stats", "queue_row"]


@dataclass(slots=True)
class Pending:
    """An outcome whose audit row may not be durable yet; :meth:`ReceiverBase.settle` answers."""

    outcome: Outcome
    #: The queued audit row (``None``: nothing to wait for: no trail, or not audited);
    #: an asyncio future when an event loop queued it.
    audit: Future[int] | asyncio.Future[int] | None = None
    #: An accepted body, its expiry and whether it declared ``qos`` >= 1, remembered as a
    #: known copy once audited.
    memo: tuple[bytes, float, bool] | None = None
    #: A fresh, authentic ESTOP: delivered even when its audit row cannot be made durable.
    estop: bool = False
    #: The outcome's audit row, for the driver to queue (kept to be spilled if it fails).
    row: AuditRow | None = None


def patience(pending: Pending) -> float | None:
    """How long an answer waits for its audit row (``None``: until the row is durable or
    failed): a fresh ESTOP's at most :data:`SAFETY_WAIT_S` (then delivered flagged, its
    row withdrawn and spilled)."""
    return SAFETY_WAIT_S if pending.estop else None


def wait(pending: Pending) -> BaseException | None:
    """Block until the audit row is durable: ``None``, or why it could not be made so
    (``TimeoutError``: not within :func:`patience`; the row is still queued)."""
    audit = pending.audit
    if audit is None:
        return None
    assert isinstance(audit, Future), "a row queued by an event loop is awaited there"
    try:
        audit.result(patience(pending))
    except Exception as exc:  # any failure to record is the answer
        return exc
    return None


def queue_row(audit: AuditLog | None, pending: Pending, *, on_loop: bool) -> Pending:
    """Queue ``pending``'s row for the trail's next group commit (``on_loop``: an asyncio
    future the running loop awaits; a fresh ESTOP's is always a thread's future, withdrawn
    if it is not written in time); a trail that is closing fails the row at once."""
    if audit is None or pending.row is None:
        return pending
    try:
        pending.audit = audit.append_later(pending.row, on_loop=on_loop and not pending.estop)
    except RuntimeError as exc:
        failed: Future[int] = Future()
        failed.set_exception(exc)
        pending.audit = failed
    return pending


@dataclass(frozen=True, slots=True)
class _Copy:
    """What is remembered of an accepted body (never the body itself)."""

    length: int
    expires_at: float
    msg_id: str | None
    type: int | None  # the type the policy applied (the message's class)
    sender: str | None
    qos: bool  # declared qos >= 1: a copy goes on to step 3, where its retry is decided


@dataclass
class Stats:
    """Counters for metrics: accepted, rejected by code, warnings, refusals folded."""

    accepted: int = 0
    rejected: Counter[str] = field(default_factory=Counter)
    warnings: Counter[str] = field(default_factory=Counter)
    #: Refusals given no row of their own (rate limit or disk floor; summarised later).
    unaudited: int = 0
    audit_failures: int = 0
    losses: int = 0
    #: QoS retransmissions answered with their original answer (also in ``rejected``).
    retries: int = 0
    #: ESTOPs delivered while their audit row could not be written; of them, rows spilled.
    held_estops: int = 0
    spilled: int = 0
    #: Commands refused because free space was below the second floor.
    disk_refusals: int = 0
    #: ESTOP rows neither the trail nor its spill could take (each one logged whole).
    held_dropped: int = 0


class ReceiverBase:
    """One robot's receive state and the rules both drivers follow; thread-safe (the window
    and stores are atomic).  Its methods decide and return :class:`Pending` values; the
    drivers queue their rows and answer."""

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
        space: DiskSpace | None = None,
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
        self.steps = Steps(
            config, keys, jwt=jwt, jwt_required=jwt_required, versions=versions,
            max_bytes=max_bytes,
        )  # fmt: skip
        self.stats = Stats()
        self._copies: dict[int, _Copy] = {}
        self.answers = AnswerMemo(config.msg_id_cache_size)
        #: How long an event loop waits for the answer of an original still in flight.
        self.answer_wait_s = 5.0
        #: Free space under the trail and its floors (``None``: not watched).
        self.space = space
        self.refusals = RefusalAuditor(
            audit, self.clock, per_s=invalid_audit_per_s, authentic_per_s=AUDIT_PER_S,
            log=log, quiet=None if space is None else space.low,
        )  # fmt: skip
        reason = getattr(self.cache.store, "loss_reason", None)
        if reason is not None:  # noticed while the store opened (a lost or rolled-back file)
            self._audit_loss(str(reason))

    # --- the steps between the core's calls ------------------------------------------------

    def _check(self, checked: Checked) -> ReplayAttackError | None:
        """Step 3, the replay check (records nothing): its refusal, as a value (a flood of
        replays raises nothing on its way to the answer)."""
        env = checked.env
        verdict = self.cache.try_check(env.msg_id, env.seconds, *checked.cls)
        return verdict.error() if isinstance(verdict, Refusal) else None

    def _check_and_authenticate(
        self, checked: Checked, headers: Mapping[str, str] | None
    ) -> NeedsCommit | Done:
        """Steps 3-6: the replay check (records nothing), then the core's token, signature
        and scopes."""
        return self.steps.authenticate(checked, self._check(checked), headers)

    def _floor(self, step: NeedsCommit | Done) -> NeedsCommit | Done:
        """Below the disk's second floor only an ESTOP goes on to its commit."""
        if self.space is None or not isinstance(step, NeedsCommit) or is_estop(*step.cls):
            return step
        reason = self.space.reason()
        if reason is None:
            return step
        self.stats.disk_refusals += 1
        return step.refused(StateUnavailableError(reason))

    def _accept(
        self, raw: bytes, need: NeedsCommit, verdict: Verdict, *, audited: bool = False
    ) -> Pending:
        """A committed message: its answer expected, its row to queue (``audited``: its row
        was put with its entry, durable already)."""
        accepted = self.steps.accept(need, verdict)
        if accepted.entry is not None:
            self.answers.expect(need.env.msg_id, accepted.entry, self.clock.wall())
        memo = (raw, verdict.expires_at, accepted.qos) if accepted.memo else None
        pending = Pending(accepted.outcome, memo=memo, estop=verdict.estop)
        return pending if audited else self._with_row(pending)

    # --- one durable trip: an accepted command's entry and row as one operation -------------

    def _paired_store(self, step: NeedsCommit) -> SqliteStore | None:
        """The SQLite store whose next batch takes ``step``'s entry and its accepted row as
        ONE operation (:class:`~antireplay.state.outbox.Paired`: one fsync, one answer), or
        ``None``: two apart (no trail, a trail not in that store's outbox, or an ESTOP,
        whose bounded waits and spill need them apart).  Both drivers ask here."""
        audit = self.audit
        if audit is None or is_estop(*step.cls) or not audit.pairs_with(self.cache.store):
            return None
        return cast(SqliteStore, self.cache.store)

    def _pair(self, step: NeedsCommit) -> tuple[Verdict, float, Callable[[Seen], str | None]]:
        """The paired commit's first half: the plan on a fresh ``now`` (raises the
        refusal the known fence or watermark gives) and the row the store's writer puts
        with the entry, in the same transaction, only if the window's own pure ``decide``
        accepts what the commit found (what :meth:`ReplayCache.finish_commit` judges after)."""
        cache = self.cache
        plan, now = cache.begin_commit(step.env.msg_id, step.env.seconds, *step.cls)
        decide = cache.policy.decide
        template = accepted_row(step, self.clock.wall())

        def row(seen: Seen) -> str | None:
            verdict = decide(
                plan, seen.expiry, seen.watermark, seen.fence, seen.recorded, seen.full, now
            )
            if isinstance(verdict, Refusal):
                return None
            warning = verdict.warning
            return stored_json(template if warning is None else replace(template, warning=warning))

        return plan, now, row

    def _paired(
        self,
        raw: bytes,
        step: NeedsCommit,
        *,
        plan: Verdict,
        now: float,
        found: Seen | StateUnavailableError,
        put: int,
    ) -> Pending | Done:
        """The paired commit's second half: the accepted message (its row durable already
        when the writer ``put`` it: a row id, 0 for none), or the refusal for the driver
        to answer."""
        try:
            verdict = self.cache.finish_commit(plan, now, found)
        except ReplayAttackError as exc:
            return step.refused(exc)
        return self._accept(raw, step, verdict, audited=put > 0)

    def _with_row(self, pending: Pending) -> Pending:
        """``pending`` with its audit row (always recorded: not a refusal's)."""
        if self.audit is not None:
            pending.row = audit_row(pending.outcome, self.clock.wall())
        return pending

    def _retry_entry(self, done: Done) -> tuple[Entry | None, Done]:
        """For a ``REPLAY_DETECTED`` message that declares ``qos`` >= 1 and carries the
        same authenticated content as the message accepted under its msg_id: that
        message's answer entry (held or in flight; no signature check, answers.py).
        Otherwise ``None`` and the refusal to send."""
        env = done.env
        if env is None or not may_retry(done.error, env):
            return None, done
        entry = self.answers.find(env, self.clock.wall())
        if entry is None:
            return None, not_held(done, "original answer not held here")
        return entry, done

    def _answer_retry(self, entry: Entry, held: HeldAnswer, done: Done) -> Pending:
        """A QoS retransmission: the original answer, audited as a refused replay
        (``REPLAY_DETECTED``, warning ``QOS_RETRY``) by the original's verified signer."""
        exc = ReplayDetectedError(
            "QoS retransmission: the original answer, not executed again", detail=QOS_RETRY
        )
        outcome = self.steps.refuse(Done(exc, done.env, entry.signer, done.msg_type))
        outcome.retry = held  # status, nack: still 409, what a retry-unaware transport sends
        self.stats.rejected[exc.code] += 1
        self.stats.retries += 1
        return self._refusal_row(Pending(outcome))

    def _reject(self, done: Done, copy: _Copy | None = None) -> Pending:
        """The NACK outcome of a refusal; ``copy`` describes a memo hit (nothing parsed)."""
        outcome = self.steps.refuse(done, None if copy is None else copy.msg_id)
        self.stats.rejected[done.error.code] += 1
        return self._refusal_row(Pending(outcome), None if copy is None else copy.sender)

    def _refusal_row(self, pending: Pending, sender: str | None = None) -> Pending:
        """A refusal's row if the auditor gives it one, else folded into its summary."""
        if self.audit is None:
            return pending
        outcome = pending.outcome
        claimed = row_sender(outcome, sender)
        if self.refusals.admit(
            authentic=outcome.signer is not None, code=outcome.code, sender=claimed,
            msg_id=outcome.msg_id,
        ):  # fmt: skip
            pending.row = audit_row(outcome, self.clock.wall(), claimed)  # built once admitted
        else:
            self.stats.unaudited += 1
        return pending

    def _upstream_failure(self, outcome: Outcome, error: ReplayAttackError) -> Pending:
        """An accepted message's upstream failed (``UPSTREAM_FAILED``, warning
        ``delivered=…``, under its verified sender): its row, always recorded."""
        failed = self.steps.refuse(Done(error, outcome.envelope, outcome.signer, outcome.msg_type))
        failed.msg_id = outcome.msg_id
        return self._with_row(Pending(failed))

    # --- step 0: the memo of accepted bodies ------------------------------------------------

    def _remember_copy(self, raw: bytes, expires_at: float, qos: bool, outcome: Outcome) -> None:
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
        sender = None if outcome.signer is None else f"kid:{outcome.signer.kid}"  # as claimed
        copies[hash(raw)] = _Copy(
            len(raw), expires_at, outcome.msg_id, outcome.msg_type, sender, qos
        )

    def _known_copy(self, raw: bytes) -> Pending | None:
        """Step 0: a byte-identical copy of an accepted message refused with no parsing, no
        lock and no I/O (its row still to queue); ``None``: not a known copy."""
        copy = self._copies.get(hash(raw)) if type(raw) is bytes else None
        if copy is None or copy.qos or copy.length != len(raw):
            return None
        if copy.expires_at < self.clock.wall():
            return None
        exc = ReplayDetectedError("an identical message was already accepted")
        return self._reject(Done(exc, None, None, copy.type), copy)

    # --- the answer ---------------------------------------------------------------------------

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

    def settle(self, pending: Pending, failure: BaseException | None) -> Outcome:
        """The answer, once the outcome's audit row is durable (``failure`` is ``None``) or
        could not be made durable.  Only an accepted message whose row failed blocks (its
        refusal is audited in turn, on this thread): run that case off the event loop."""
        outcome = pending.outcome
        if failure is not None:
            self.stats.audit_failures += 1
            if not outcome.accepted:
                return outcome  # the rejection stands; it could not be recorded (yet)
            warning = estop_survives(pending.estop, outcome.warning, WarningCode.AUDIT_UNAVAILABLE)
            if warning is None:
                # Nothing accepted may be missing from the audit trail: refuse to act on it.
                # Its msg_id is spent; the sender resends with a new one once the disk is back.
                if outcome.envelope is not None and type(outcome.envelope.msg_id) is str:
                    self.answers.drop(outcome.envelope.msg_id)  # no answer to hold
                exc = StateUnavailableError(f"audit trail unavailable: {failure}")
                done = Done(exc, outcome.envelope, outcome.signer, outcome.msg_type)
                refusal = queue_row(self.audit, self._reject(done), on_loop=False)
                return self.settle(refusal, wait(refusal))
            self._hold(pending, failure, warning)  # safety beats the audit trail
        if outcome.accepted:
            self.stats.accepted += 1
            if outcome.warning:
                self.stats.warnings[outcome.warning] += 1
            elif pending.memo is not None and outcome.envelope is not None:
                self._remember_copy(*pending.memo, outcome)
        return outcome

    @property
    def held_rows(self) -> int:
        """Audit rows of delivered ESTOPs spilled, waiting for the trail to be writable."""
        return 0 if self.audit is None else self.audit.spilled

    def _hold(self, pending: Pending, failure: BaseException, warning: str) -> None:
        """Deliver an ESTOP whose audit row failed: warn, spill its row (said once per
        outage); a row the spill cannot take is logged whole, its only record, and counted."""
        outcome = pending.outcome
        outcome.warning = warning
        self.stats.held_estops += 1
        if pending.row is None or self.audit is None:
            return
        row = replace(pending.row, warning=warning)
        audit = pending.audit
        if isinstance(failure, TimeoutError) and isinstance(audit, Future) and not audit.cancel():
            # Already in a batch (cannot be withdrawn): it lands, or is spilled if it fails.
            audit.add_done_callback(lambda done: self._spill_late(done, row))
            return
        self._spill(row, failure)

    def _spill_late(self, done: Future[int], row: AuditRow) -> None:
        """An ESTOP row's batch finished after its answer: spilled only if it failed."""
        failure = None if done.cancelled() else done.exception()
        if failure is not None:
            self._spill(row, failure)

    def _spill(self, row: AuditRow, failure: BaseException) -> None:
        """Keep one delivered ESTOP's row in the spill (merged into the trail later)."""
        assert self.audit is not None
        first = self.held_rows == 0
        if not self.audit.spill(row):
            self.stats.held_dropped += 1
            log.error("audit trail and its spill unavailable (%s); ESTOP row: %s", failure, row)
            return
        self.stats.spilled += 1
        if first:
            log.error(
                "audit trail unavailable (%s): ESTOP delivered, its row spilled to the reserved "
                "file until the trail takes a row again; other messages get STATE_UNAVAILABLE",
                failure,
            )

    def close(self) -> None:
        """Write the folded refusals' summary rows, then close the audit trail."""
        if self.audit is not None:
            self.refusals.close()
            self.audit.close()

    def _audit_loss(self, reason: str) -> None:
        """A store noticed it may have forgotten accepted messages: fenced, and on the record."""
        self.stats.losses += 1
        if self.audit is None:
            return
        try:
            self.audit.append(
                AuditRow(self.clock.wall(), "state", WarningCode.STATE_LOST, reason[:200])
            )
        except StateUnavailableError:
            self.stats.audit_failures += 1


def not_held(done: Done, why: str) -> Done:
    """The plain ``REPLAY_DETECTED`` refusal of a retry whose original answer is not here."""
    exc = ReplayDetectedError(f"msg_id already accepted; {why}")
    return Done(exc, done.env, done.signer, done.msg_type)
