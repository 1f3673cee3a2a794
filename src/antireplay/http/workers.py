"""The few threads that do a request's blocking work for the event loop.

Parsing, the store read and the signature check block; the event loop must not.  A
request hands that work to :class:`Workers` once and awaits an asyncio future; the state
commit and the audit row are not done here (they are group-committed and awaited on the
loop).  A few threads suffice: nobody waits for a commit in them, and the signature check
releases the GIL, so a crowd of threads would only fight over it.  A result goes back as
one ``call_soon_threadsafe`` into the caller's future, without ``concurrent.futures`` in
between (its per-call futures and locks cost the loop more than the hand-off itself).  A
future already cancelled (the client went away) is left alone; a closed loop has nobody
left to answer.
"""

from __future__ import annotations

import asyncio
import contextlib
import queue
import threading
from collections.abc import Callable
from typing import Any


class Workers:
    """The threads that parse, read the store and check signatures for the event loop."""

    def __init__(self, count: int) -> None:
        self._queue: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()
        self._threads = [
            threading.Thread(target=self._serve, name=f"antireplay-receive-{i}", daemon=True)
            for i in range(count)
        ]
        for thread in self._threads:
            thread.start()

    def __call__(self, fn: Callable[..., Any], *args: Any) -> asyncio.Future[Any]:
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        self._queue.put((loop, future, fn, args))
        return future

    def _serve(self) -> None:
        while (job := self._queue.get()) is not None:
            loop, future, fn, args = job
            try:
                result, error = fn(*args), None
            except BaseException as exc:  # delivered to the awaiting request, raised there
                result, error = None, exc
            with contextlib.suppress(RuntimeError):  # a closed loop has nobody left to answer
                loop.call_soon_threadsafe(_resolve, future, result, error)

    def shutdown(self) -> None:
        for _ in self._threads:
            self._queue.put(None)
        for thread in self._threads:
            thread.join(timeout=30)


_Job = tuple[asyncio.AbstractEventLoop, "asyncio.Future[Any]", Callable[..., Any], tuple[Any, ...]]


def _resolve(future: asyncio.Future[Any], result: Any, error: BaseException | None) -> None:
    if future.done():  # cancelled: the client went away
        return
    if error is None:
        future.set_result(result)
    else:
        future.set_exception(error)
