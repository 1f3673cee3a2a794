"""The RCAN receive path: one sans-I/O core (:mod:`~antireplay.rcan.steps`), two drivers.

Theory of operation
-------------------
:class:`Receiver` runs RCAN §8.3's check -> authenticate -> commit through
:class:`~antireplay.rcan.steps.Steps`; the rules between the core's calls (the memo of
accepted bodies, the disk floor, QoS retransmissions, the refusal auditor, what an audit
failure does to the answer) are :class:`~antireplay.rcan.receive_shared.ReceiverBase`'s,
written once.  This module is the thread driver: :meth:`Receiver.receive` parses, checks,
authenticates, commits (:class:`~antireplay.state.replay.ReplayCache`) and queues the
audit row on the calling thread, then blocks until the row is durable; with the trail's
outbox in the SQLite store an accepted command's entry and row are ONE operation of one
batch (:meth:`~ReceiverBase._pair`, the rule both drivers share).  The event-loop
driver (:class:`~antireplay.rcan.receive_loop.LoopDriver`) serves
:meth:`Receiver.receive_async`: it refuses junk and known replays on the loop and hands a
thread at most one job (the signature).

No answer goes out before its audit row is durable: :meth:`Receiver.receive_later` queues
the row for the trail's next group commit and :meth:`~ReceiverBase.settle` answers once
it is.  A fresh ESTOP waits for its commit and its row at most ``SAFETY_WAIT_S`` each (a
row not written by then is withdrawn and spilled, or, already in a batch, spilled only if
that batch fails).  Nothing raises for anything a peer can send.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import cached_property

from antireplay.core.errors import ReplayAttackError, StateUnavailableError
from antireplay.core.window import Seen
from antireplay.rcan.receive_loop import LoopDriver
from antireplay.rcan.receive_shared import (
    HELD_ROWS,
    SHAPE_ERRORS,
    Pending,
    ReceiverBase,
    Stats,
    not_held,
    queue_row,
    wait,
)
from antireplay.rcan.steps import Checked, Done, NeedsCommit, Outcome
from antireplay.state import Offload
from antireplay.state.sqlite import SqliteStore

__all__ = ["HELD_ROWS", "SHAPE_ERRORS", "Offload", "Outcome", "Pending", "Receiver", "Stats"]


class Receiver(ReceiverBase):
    """One robot's receive path; thread-safe (the window and stores are atomic)."""

    def receive(self, raw: bytes, headers: Mapping[str, str] | None = None) -> Outcome:
        """Run the §8.3 steps; never raises for anything a peer can send."""
        pending = self.receive_later(raw, headers)
        return self.settle(pending, wait(pending))

    def receive_later(self, raw: bytes, headers: Mapping[str, str] | None = None) -> Pending:
        """Every step through the commit; the outcome's audit row is queued for the next
        group commit, not awaited.  Answer with :meth:`settle` once ``Pending.audit`` is
        done (:meth:`receive` blocks on it)."""
        return queue_row(self.audit, self._decide(raw, headers), on_loop=False)

    def _decide(self, raw: bytes, headers: Mapping[str, str] | None) -> Pending:
        copy = self._known_copy(raw)
        if copy is not None:
            return copy
        parsed = self.steps.parse(raw)
        step = (
            self._check_and_authenticate(parsed, headers) if isinstance(parsed, Checked) else parsed
        )
        step = self._floor(step)
        if isinstance(step, NeedsCommit):
            paired = self._paired_store(step)
            if paired is not None:
                return self._commit_paired(raw, step, paired)
            env = step.env
            try:
                verdict = self.cache.commit(env.msg_id, env.seconds, *step.cls)
            except ReplayAttackError as exc:
                step = step.refused(exc)
            else:
                return self._accept(raw, step, verdict)
        return self._refused(step)

    def _refused(self, done: Done) -> Pending:
        """The refusal, or a QoS retransmission's original answer when it is held here."""
        entry, done = self._retry_entry(done)
        if entry is not None and entry.answer is not None:
            return self._answer_retry(entry, entry.answer, done)
        if entry is not None:  # in flight: only an event loop waits (receive_async)
            done = not_held(done, "original answer not held here yet (still in flight)")
        return self._reject(done)

    def _commit_paired(self, raw: bytes, step: NeedsCommit, store: SqliteStore) -> Pending:
        """One durable trip, the loop driver's rule (:meth:`ReceiverBase._pair`,
        :meth:`ReceiverBase._paired`): the entry and its accepted row in one operation of
        the store's next batch, waited for on this thread; a refusal goes on as below."""
        try:
            plan, now, row = self._pair(step)
        except ReplayAttackError as exc:
            return self._refused(step.refused(exc))
        found: Seen | StateUnavailableError
        try:
            found, put = store.commit_with_row(plan.msg_id, plan.expires_at, now, row)
        except StateUnavailableError as exc:
            found, put = exc, 0
        got = self._paired(raw, step, plan=plan, now=now, found=found, put=put)
        return self._refused(got) if isinstance(got, Done) else got

    # --- the event-loop driver's entry points ------------------------------------------------

    @cached_property
    def loop(self) -> LoopDriver:
        """The event-loop driver over this receiver's state."""
        return LoopDriver(self)

    async def receive_async(
        self,
        raw: bytes,
        headers: Mapping[str, str] | None = None,
        offload: Offload | None = None,
        urgent: Offload | None = None,
    ) -> Outcome:
        """:meth:`receive` for an event loop (:meth:`LoopDriver.receive`)."""
        return await self.loop.receive(raw, headers, offload, urgent)

    async def receive_later_async(
        self,
        raw: bytes,
        headers: Mapping[str, str] | None = None,
        offload: Offload | None = None,
        urgent: Offload | None = None,
    ) -> Pending:
        """:meth:`receive_later` for an event loop (:meth:`LoopDriver.receive_later`)."""
        return await self.loop.receive_later(raw, headers, offload, urgent)

    def reject_known_copy(self, raw: bytes) -> Pending | None:
        """Step 0 on an event loop (:meth:`LoopDriver.reject_known_copy`)."""
        return self.loop.reject_known_copy(raw)

    async def record_upstream_failure(self, outcome: Outcome, error: ReplayAttackError) -> None:
        """Audit an accepted message's upstream failure
        (:meth:`LoopDriver.record_upstream_failure`)."""
        await self.loop.record_upstream_failure(outcome, error)
