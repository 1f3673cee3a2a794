"""Group commit: concurrent writers share one transaction and one fsync, nobody is answered early.

Theory of operation
-------------------
Durability costs an ``fsync``.  Taking one per request, one request at a time under a lock,
turns a burst of requests, and worse a replay flood whose every rejection is
audited, into an fsync flood.  Databases answer this with group commit, and so
do we, in exactly one place: :class:`GroupCommitter`.

* Callers :meth:`~GroupCommitter.submit` an operation and block until *their*
  operation is durable (or failed), or :meth:`~GroupCommitter.enqueue` it and
  keep its future; an event loop calls :meth:`~GroupCommitter.enqueue_async`
  and awaits an asyncio future instead, holding no thread: the writer resolves
  every such waiter of a batch with one call into their loop, not one each.
  A single writer thread takes the first waiting operation, drains whatever
  else has queued up meanwhile (at most ``max_batch``), and hands the batch to
  the owner's ``run_batch``, which executes it in one transaction with one
  commit and returns one result per operation, in order.  Only then are the callers woken.
* Operations in a batch run sequentially inside that transaction, so two
  racers on one key still get exactly one winner; the batch is atomic, so a
  ``kill -9`` at any moment leaves either the whole batch durable (its callers
  may not have been answered: safe, a retry is refused as a replay) or none of
  it (no caller was answered).
* A batch that fails raises the same error in every caller of that batch.
* A thread's caller that stops waiting may withdraw its operation: ``Future.cancel()``
  succeeds only while it is still queued (the writer marks each taken future running), so a
  withdrawn operation is never committed and one that was not is committed as usual.
* Under no concurrency a batch is one operation: the cost is one thread
  hand-off (tens of microseconds), against an fsync of a hundred or more.

Used by :class:`~antireplay.state.sqlite.SqliteStore` (seen-set commits and the audit
outbox's rows, :mod:`antireplay.state.outbox`) and :class:`~antireplay.audit.AuditLog`
(audit rows, or the outbox's drains).
"""

from __future__ import annotations

import asyncio
import contextlib
import queue
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Generic, TypeVar, cast

Op = TypeVar("Op")
R = TypeVar("R")


class _Slot(Generic[Op, R]):
    """One caller's operation and the future its result or error is delivered to."""

    __slots__ = ("future", "op")

    def __init__(self, op: Op, future: Future[R] | asyncio.Future[R]) -> None:
        self.op = op
        self.future = future


def _deliver(
    waiters: list[tuple[asyncio.Future[R], R | None]], error: BaseException | None
) -> None:
    """On the waiters' loop: one batch's results (or its error) into their futures."""
    for waiter, result in waiters:
        if waiter.done():  # cancelled: its caller went away
            continue
        if error is None:
            waiter.set_result(cast(R, result))
        else:
            waiter.set_exception(error)


def _taken(future: Future[R] | asyncio.Future[R]) -> bool:
    """Whether the writer takes this operation: a thread's future not withdrawn (cancelled)
    by its caller, marked running so that it can no longer be; an event loop's always (a
    cancelled waiter only goes unanswered)."""
    return not isinstance(future, Future) or future.set_running_or_notify_cancel()


class GroupCommitter(Generic[Op, R]):
    """One writer thread; ``run_batch(ops) -> results`` is called with every queued operation."""

    def __init__(
        self, run_batch: Callable[[Sequence[Op]], list[R]], *, name: str, max_batch: int = 512
    ) -> None:
        self._run_batch = run_batch
        self._queue: queue.SimpleQueue[_Slot[Op, R] | None] = queue.SimpleQueue()
        self.max_batch = max_batch
        self.batches = 0
        self.operations = 0
        self._closed = False
        self._gate = threading.Lock()
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def submit(self, op: Op) -> R:
        """Queue ``op`` and wait until it is durable; its result, or the batch's error."""
        return self.enqueue(op).result()

    def enqueue(self, op: Op) -> Future[R]:
        """Queue ``op`` without waiting: an event loop awaits the future
        (``asyncio.wrap_future``) instead of blocking a thread."""
        future: Future[R] = Future()
        self._put(_Slot(op, future))
        return future

    def enqueue_async(self, op: Op) -> asyncio.Future[R]:
        """Queue ``op`` from a running event loop; await the result (no thread held)."""
        waiter: asyncio.Future[R] = asyncio.get_running_loop().create_future()
        self._put(_Slot(op, waiter))
        return waiter

    def _put(self, slot: _Slot[Op, R]) -> None:
        with self._gate:  # a slot queued before close()'s sentinel is always committed
            if self._closed:
                raise RuntimeError("group committer closed")
            self._queue.put(slot)

    def close(self) -> None:
        """Finish what is queued, then stop the writer."""
        with self._gate:
            if self._closed:
                return
            self._closed = True
            self._queue.put(None)
        self._thread.join(timeout=30)

    def _loop(self) -> None:
        while True:
            first = self._queue.get()
            if first is None:
                return
            batch = [first]
            stop = False
            while len(batch) < self.max_batch:
                try:
                    more = self._queue.get_nowait()
                except queue.Empty:
                    break
                if more is None:
                    stop = True
                    break
                batch.append(more)
            self._commit(batch)
            if stop:
                return

    def _commit(self, queued: list[_Slot[Op, R]]) -> None:
        batch = [slot for slot in queued if _taken(slot.future)]
        if not batch:
            return
        error: BaseException | None = None
        results: list[R | None]
        try:
            results = list(self._run_batch([slot.op for slot in batch]))
            if len(results) != len(batch):
                raise RuntimeError("run_batch returned a result count unlike its batch")
        except BaseException as exc:  # every caller of a failed batch gets its error
            error, results = exc, [None] * len(batch)
        else:
            self.batches += 1
            self.operations += len(batch)
        loops: dict[asyncio.AbstractEventLoop, list[tuple[asyncio.Future[R], R | None]]] = {}
        for slot, result in zip(batch, results, strict=True):
            future = slot.future
            if isinstance(future, Future):
                if error is None:
                    future.set_result(cast(R, result))
                else:
                    future.set_exception(error)
            else:
                loops.setdefault(future.get_loop(), []).append((future, result))
        for loop, waiters in loops.items():
            with contextlib.suppress(RuntimeError):  # a closed loop has nobody left to answer
                loop.call_soon_threadsafe(_deliver, waiters, error)
