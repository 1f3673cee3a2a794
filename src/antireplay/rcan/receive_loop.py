"""The RCAN event-loop driver: the receive steps on an asyncio loop, a thread for at most
one job per message.

Theory of operation
-------------------
:class:`LoopDriver` drives the same sans-I/O core (:class:`~antireplay.rcan.steps.Steps`)
and the same rules (:class:`~antireplay.rcan.receive_shared.ReceiverBase`) as the thread
driver, holding no thread while it waits.  A byte-identical copy is refused on the loop,
and so is what fails the parse; the replay check runs on the loop where the store answers
in process (memory, SQLite: :data:`LOCAL_BACKENDS`), so a known replay is refused with no
hand-off; the rest (the signature, and a network store's check) is ONE job in
``offload(fn, *args)`` (default: the loop's executor), a fresh SAFETY message's in
``urgent`` (the lane the gateway's workers take first; on a network store, chosen before
its check).  The store's ``commit_async`` and every audit row are awaited on the loop.
With the trail's outbox in the SQLite store, an accepted command's entry and row are ONE
operation of one batch (one fsync, one answer back to the loop), by the rule the thread
driver follows too (:meth:`ReceiverBase._pair`); an ESTOP's stay apart (their bounded
waits and the spill need them so).

A QoS retransmission whose original is still in flight waits on the loop for the
original's answer (at most ``answer_wait_s``).  An accepted message whose audit row failed
is settled on a thread (its refusal is audited in turn; an ESTOP's row is spilled to a
file): that one case leaves the loop, in the urgent lane for an ESTOP.
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping

from antireplay.core.errors import ReplayAttackError, StateUnavailableError
from antireplay.core.messages import MessageType
from antireplay.core.window import Seen
from antireplay.rcan.receive_shared import (
    Pending,
    ReceiverBase,
    not_held,
    patience,
    queue_row,
)
from antireplay.rcan.steps import Done, NeedsCommit, Outcome, may_retry
from antireplay.state import Offload, in_executor
from antireplay.state.sqlite import SqliteStore

#: Stores whose replay check an event loop runs itself (no network round trip).
LOCAL_BACKENDS = frozenset({"memory", "sqlite"})

__all__ = ["LOCAL_BACKENDS", "LoopDriver", "durable"]


async def durable(pending: Pending) -> BaseException | None:
    """Wait on the loop, holding no thread, until the audit row is durable: ``None``, or
    why it could not be made so (``TimeoutError``: not within its patience)."""
    audit = pending.audit
    if audit is None:
        return None
    waiter = audit if isinstance(audit, asyncio.Future) else asyncio.wrap_future(audit)
    wait_s = patience(pending)
    try:
        await (waiter if wait_s is None else asyncio.wait_for(asyncio.shield(waiter), wait_s))
    except Exception as exc:  # any failure to record is the answer
        return exc
    return None


class LoopDriver:
    """The event-loop driver of one :class:`ReceiverBase`'s state."""

    def __init__(self, receiver: ReceiverBase) -> None:
        self.receiver = receiver
        #: Whether the loop runs the replay check itself: the store answers in process (a
        #: dict, a SQLite read from the page cache); a network store's round trip stays on
        #: the thread, in the one job with the signature.
        self.check_on_loop = receiver.cache.store.backend in LOCAL_BACKENDS

    def _queued(self, pending: Pending) -> Pending:
        """Queue the row as an asyncio future of the running loop."""
        return queue_row(self.receiver.audit, pending, on_loop=True)

    async def receive(
        self, raw: bytes, headers: Mapping[str, str] | None, offload: Offload | None,
        urgent: Offload | None,
    ) -> Outcome:  # fmt: skip
        """The settled outcome, its audit row durable, awaited without holding a thread."""
        pending = await self.receive_later(raw, headers, offload, urgent)
        failure = await durable(pending)
        if failure is not None and pending.outcome.accepted:  # its refusal is audited: blocks
            lane = urgent if urgent is not None and pending.estop else offload or in_executor
            outcome: Outcome = await lane(self.receiver.settle, pending, failure)
            return outcome
        return self.receiver.settle(pending, failure)

    async def receive_later(
        self, raw: bytes, headers: Mapping[str, str] | None, offload: Offload | None,
        urgent: Offload | None,
    ) -> Pending:  # fmt: skip
        """Every step through the commit, a thread handed at most ONE job; the audit row
        queued for the loop to await (answer with ``settle`` once ``Pending.audit`` is done)."""
        copy = self.reject_known_copy(raw)
        if copy is not None:
            return copy
        r = self.receiver
        run = offload or in_executor
        parsed = r.steps.parse(raw)
        step: NeedsCommit | Done
        if isinstance(parsed, Done):
            step = parsed
        elif not self.check_on_loop:
            lane = urgent if urgent is not None and parsed.cls[0] == MessageType.SAFETY else run
            step = await lane(r._check_and_authenticate, parsed, headers)
        else:
            replayed = r._check(parsed)
            if replayed is not None and not may_retry(replayed, parsed.env):
                step = r.steps.authenticate(parsed, replayed, headers)  # refused: no crypto
            else:
                fresh_safety = replayed is None and parsed.cls[0] == MessageType.SAFETY
                lane = urgent if urgent is not None and fresh_safety else run
                step = await lane(r.steps.authenticate, parsed, replayed, headers)
        step = r._floor(step)
        if isinstance(step, Done):
            return await self._refuse(step)
        paired = r._paired_store(step)
        if paired is not None:
            return await self._commit_paired(raw, step, paired)
        env = step.env
        try:
            verdict = await r.cache.commit_async(env.msg_id, env.seconds, *step.cls, run)
        except ReplayAttackError as exc:
            return await self._refuse(step.refused(exc))
        return self._queued(r._accept(raw, step, verdict))

    async def _commit_paired(self, raw: bytes, step: NeedsCommit, store: SqliteStore) -> Pending:
        """One durable trip (:meth:`ReceiverBase._pair`, :meth:`ReceiverBase._paired`, the
        rule both drivers share): the entry and its accepted row in one operation of the
        store's next batch, awaited on the loop; a refusal's row is queued apart."""
        r = self.receiver
        try:
            plan, now, row = r._pair(step)
        except ReplayAttackError as exc:
            return await self._refuse(step.refused(exc))
        found: Seen | StateUnavailableError
        try:
            found, put = await store.commit_with_row_async(plan.msg_id, plan.expires_at, now, row)
        except StateUnavailableError as exc:
            found, put = exc, 0
        got = r._paired(raw, step, plan=plan, now=now, found=found, put=put)
        return await self._refuse(got) if isinstance(got, Done) else self._queued(got)

    def reject_known_copy(self, raw: bytes) -> Pending | None:
        """Step 0 without blocking: a byte-identical copy of an accepted message is refused
        with no parsing, no lock and no I/O; its audit row is queued for the next group
        commit.  ``None``: not a known copy, run :meth:`receive_later`."""
        copy = self.receiver._known_copy(raw)
        return None if copy is None else self._queued(copy)

    async def _refuse(self, done: Done) -> Pending:
        """The refusal, or a QoS retransmission's original answer, awaited on the loop
        while the original is still in flight (at most ``answer_wait_s``)."""
        r = self.receiver
        entry, done = r._retry_entry(done)
        if entry is not None:
            held = await r.answers.wait(entry, r.answer_wait_s)
            if held is not None:
                return self._queued(r._answer_retry(entry, held, done))
            done = not_held(done, "original answer not held here (none arrived in time)")
        return self._queued(r._reject(done))

    async def record_upstream_failure(self, outcome: Outcome, error: ReplayAttackError) -> None:
        """Audit that an accepted message's upstream failed, the row queued with the others
        and durable before the failure is answered; a row that cannot be written is counted."""
        pending = self._queued(self.receiver._upstream_failure(outcome, error))
        if await durable(pending) is not None:
            self.receiver.stats.audit_failures += 1  # the failure is still answered
