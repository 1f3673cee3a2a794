"""The few threads that check signatures for the event loop: two lanes, results in batches.

Theory of operation
-------------------
A request's signature check blocks; the event loop must not.  The receive driver parses
and runs the replay check on the loop (cheap, no I/O it waits for) and hands a message
that needs cryptography to :class:`Workers` once: ``workers(fn, *args)`` returns an
asyncio future.  Thread traffic is what costs here, not the hand-off's bookkeeping, so:

* **Wake-ups:** the jobs a loop iteration submits are queued together when it ends,
  under one lock, and wake one worker only when one is idle and none is already on its
  way (a busy worker takes them when it looks again).
* **Batches:** an awake worker takes up to ``batch`` jobs, runs them and delivers their
  results to the loop with ONE ``call_soon_threadsafe`` (one loop wake-up per batch, not
  per request).  A quiet gateway's batch is one job: no added latency.
* **The urgent lane** (:meth:`Workers.first`): a fresh SAFETY message's job is queued
  at once, apart, and taken first, also between the jobs of a batch already taken (the
  rest go back to the head of the queue), so an ESTOP waits for at most the job each
  worker is running.  The class is read before the signature is checked: a forged SAFETY
  message also takes the lane, at the cost of one signature check.
* **The door** (:class:`Door`): a flood keeps the loop holding the GIL, and each thread
  hand-off of the ESTOP's check, commit and row then waits a switch interval (p99 60 ms
  under a flood where a quiet gateway takes 6).  So a fresh SAFETY message holds the door
  until its answer: from the lane on while a small budget lasts (``EARLY_PER_S``: what a
  forged flood can take), else from its authentication; requests arriving meanwhile wait
  before they start (at most :data:`HOLD_S`; another ESTOP too), and a flood's clients
  fall quiet.  The gateway lets go once the ESTOP is forwarded and answered.  One hold per
  ESTOP, not per copy: a copy of an authenticated ESTOP in flight or delivered here (its
  msg_id) is delivered as the ESTOP invariant says but holds nothing; before its signature
  check it still spends the early budget like any SAFETY message.

A future already cancelled (the client went away) is left alone; a closed loop has
nobody left to answer.  ``shutdown`` lets the queued jobs finish, then stops the threads.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import threading
from collections.abc import Callable
from typing import Any

from antireplay.core.clock import Clock, resolve
from antireplay.core.ratelimit import TokenBucket

#: The longest a request waits at a held :class:`Door` (an ESTOP's whole answer is due by
#: then; the state's own safety wait is 0.2 s).
HOLD_S = 0.25

#: Holds taken before the signature check, per second: what a forged SAFETY flood can take.
EARLY_PER_S = 20.0
EARLY_BURST = 5.0
#: Delivered ESTOPs' msg_ids remembered, so their copies hold no door (oldest forgotten).
DELIVERED = 4096

_Job = tuple[asyncio.AbstractEventLoop, "asyncio.Future[Any]", Callable[..., Any], tuple[Any, ...]]
_Result = tuple["asyncio.Future[Any]", Any, BaseException | None]


class Workers:
    """The threads that check signatures for the event loop (see the module docstring)."""

    def __init__(self, count: int = 1, *, batch: int = 8) -> None:
        self.batch = batch
        self._ready = threading.Condition(threading.Lock())
        self._jobs: collections.deque[_Job] = collections.deque()
        self._urgent: collections.deque[_Job] = collections.deque()
        self._idle = 0  # workers waiting for a job
        self._waking = 0  # of them, notified and not yet running
        self._closed = False
        #: The jobs each loop's current iteration submitted (queued when it ends).
        self._held: dict[asyncio.AbstractEventLoop, list[tuple[collections.deque[_Job], _Job]]]
        self._held = {}
        #: Loop wake-ups (result deliveries) and jobs run, for tests and benchmarks.
        self.deliveries = 0
        self.jobs = 0
        self._threads = [
            threading.Thread(target=self._serve, name=f"antireplay-receive-{i}", daemon=True)
            for i in range(count)
        ]
        for thread in self._threads:
            thread.start()

    def __call__(self, fn: Callable[..., Any], *args: Any) -> asyncio.Future[Any]:
        """Run ``fn(*args)`` on a worker, in the ordinary lane; await the result."""
        return self._submit(self._jobs, fn, args)

    def first(self, fn: Callable[..., Any], *args: Any) -> asyncio.Future[Any]:
        """Run ``fn(*args)`` before every ordinary job queued (the urgent lane)."""
        return self._submit(self._urgent, fn, args)

    def _submit(
        self, lane: collections.deque[_Job], fn: Callable[..., Any], args: tuple[Any, ...]
    ) -> asyncio.Future[Any]:
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        if self._closed:
            raise RuntimeError("workers shut down")
        job = (loop, future, fn, args)
        if lane is self._urgent:  # queued and a worker woken now, not when the iteration ends
            with self._ready:
                lane.append(job)
                self._wake()
            return future
        held = self._held.get(loop)
        if held is None:  # the first job of this loop iteration: queued when it ends
            held = self._held[loop] = []
            loop.call_soon(self._flush, loop)
        held.append((lane, job))
        return future

    def _wake(self) -> None:
        """Under ``_ready``: wake one idle worker unless one is already on its way."""
        if self._idle > self._waking:
            self._waking += 1
            self._ready.notify()

    def _flush(self, loop: asyncio.AbstractEventLoop) -> None:
        """On the loop, once per iteration: queue the jobs its callbacks submitted, and
        wake one idle worker for all of them."""
        held = self._held.pop(loop)
        with self._ready:
            closed = self._closed  # shut down since: nobody would run them
            for lane, job in () if closed else held:
                lane.append(job)
            self._wake()  # one idle worker is enough to wake
        if closed:
            _resolve([(job[1], None, RuntimeError("workers shut down")) for _, job in held])

    def _take(self) -> tuple[list[_Job], bool] | None:
        """The next batch and whether it is urgent (one lane per batch, the urgent lane
        first), waiting for one; ``None``: shut down."""
        with self._ready:
            while not (self._urgent or self._jobs):
                if self._closed:
                    return None
                self._idle += 1
                self._ready.wait()
                self._idle -= 1
                self._waking = max(0, self._waking - 1)
            lane = self._urgent or self._jobs
            batch = [lane.popleft() for _ in range(min(len(lane), self.batch))]
            return batch, lane is self._urgent

    def _serve(self) -> None:
        while (taken := self._take()) is not None:
            batch, urgent = taken
            done: dict[asyncio.AbstractEventLoop, list[_Result]] = {}
            for index, (loop, future, fn, args) in enumerate(batch):
                if index and not urgent and self._urgent:
                    self._put_back(batch[index:])  # the urgent job runs next
                    break
                try:
                    result: _Result = (future, fn(*args), None)
                except BaseException as exc:  # delivered to the awaiting request, raised there
                    result = (future, None, exc)
                done.setdefault(loop, []).append(result)
            for loop, results in done.items():
                self._deliver(loop, results)

    def _put_back(self, rest: list[_Job]) -> None:
        with self._ready:
            self._jobs.extendleft(reversed(rest))

    def _deliver(self, loop: asyncio.AbstractEventLoop, done: list[_Result]) -> None:
        self.jobs += len(done)
        self.deliveries += 1
        with contextlib.suppress(RuntimeError):  # a closed loop has nobody left to answer
            loop.call_soon_threadsafe(_resolve, done)

    def shutdown(self) -> None:
        """Finish the queued jobs, then stop the threads."""
        with self._ready:
            self._closed = True
            self._ready.notify_all()
        for thread in self._threads:
            thread.join(timeout=30)


def _resolve(done: list[_Result]) -> None:
    """On the loop: one batch's results into their futures."""
    for future, result, error in done:
        if future.done():  # cancelled: the client went away
            continue
        if error is None:
            future.set_result(result)
        else:
            future.set_exception(error)


class Door:
    """Held by a fresh SAFETY message's request until its answer (from before its
    signature check within the early budget, else from its authentication); other
    requests :meth:`enter` after it; one hold per ESTOP, none for its copies (see the
    module docstring)."""

    def __init__(
        self,
        hold_s: float = HOLD_S,
        *,
        early_per_s: float = EARLY_PER_S,
        early_burst: float = EARLY_BURST,
        clock: Clock | None = None,
    ) -> None:
        self.hold_s = hold_s
        self._early = TokenBucket(early_per_s, resolve(clock), burst=early_burst)
        #: The tasks holding the door (an ESTOP's request each).
        self.holders: set[asyncio.Task[Any]] = set()
        self._opened: asyncio.Event | None = None
        #: The authenticated ESTOPs holding it (msg_id -> task) and those delivered since.
        self._flight: dict[str, asyncio.Task[Any]] = {}
        self._delivered: collections.OrderedDict[str, None] = collections.OrderedDict()
        #: Requests that waited at the door, and of them those it let in at ``hold_s``;
        #: holds taken once authenticated; copies that took none.
        self.waited = 0
        self.timeouts = 0
        self.holds = 0
        self.copies = 0

    async def enter(self) -> bool:
        """Return at once while nobody holds the door; else when it opens, or ``hold_s``.
        ``True``: this request waited."""
        opened = self._opened
        if opened is None:
            return False
        self.waited += 1
        try:
            await asyncio.wait_for(opened.wait(), self.hold_s)
        except asyncio.TimeoutError:
            self.timeouts += 1
        return True

    def copy(self, msg_id: object) -> bool:
        """Whether ``msg_id`` is an authenticated ESTOP's holding the door or delivered."""
        return type(msg_id) is str and (msg_id in self._flight or msg_id in self._delivered)

    def hold_early(self, msg_id: object = None) -> bool:
        """Hold the door before the signature is checked, if the budget for that allows
        (``False``: not taken now, the current task holds it already, or ``msg_id`` (as
        claimed) is a copy: it spends the budget all the same)."""
        if asyncio.current_task() in self.holders or not self._early.take():
            return False
        if self.copy(msg_id):
            return False
        self._hold()
        return True

    def hold(self, msg_id: object = None) -> bool:
        """The current task, an authenticated ESTOP's ``msg_id``, holds the door until
        :meth:`release`; a copy (that msg_id holds it or was delivered) lets go of an early
        hold and holds nothing (``False``)."""
        task = asyncio.current_task()
        if task is None:
            return False
        if type(msg_id) is str:
            if self._flight.get(msg_id, task) is not task or msg_id in self._delivered:
                self.copies += 1
                if task in self.holders:
                    self.release()
                return False
            if msg_id not in self._flight:
                self._flight[msg_id] = task
                self.holds += 1
        self._hold()
        return True

    def _hold(self) -> None:
        task = asyncio.current_task()
        if task is None or task in self.holders:
            return
        self.holders.add(task)
        if self._opened is None:
            self._opened = asyncio.Event()

    def release(self) -> None:
        """The current task lets go (its ESTOP counts as delivered); the last holder opens
        the door."""
        task = asyncio.current_task()
        self.holders.discard(task)
        for msg_id in [m for m, t in self._flight.items() if t is task]:
            del self._flight[msg_id]
            self._delivered[msg_id] = None
            if len(self._delivered) > DELIVERED:
                self._delivered.popitem(last=False)
        if not self.holders and self._opened is not None:
            self._opened.set()
            self._opened = None
