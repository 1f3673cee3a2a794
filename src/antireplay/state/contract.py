"""The store contract: the :class:`ReplayStore` protocol every backend keeps, and the one
hand-off of a blocking commit to a thread (:data:`Offload`).

The contract itself (what ``lookup``, ``commit``, ``advance``, ``advance_above``, ``forget``,
``verify`` and ``ready`` promise, and how loss is detected) is described in
:mod:`antireplay.state`; it lives in this module, apart from the package, so that the
backends and the spec grammar import it without importing the package that imports them.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Sequence
from typing import Any, Protocol, runtime_checkable

from antireplay.core.window import Seen

#: Runs ``fn(*args)`` in a thread for a running event loop to await: the one hand-off to a
#: thread (the gateway passes its worker pool; :func:`in_executor` by default).
Offload = Callable[..., Awaitable[Any]]


def in_executor(fn: Callable[..., Any], *args: Any) -> Awaitable[Any]:
    """The default :data:`Offload`: the running loop's default executor."""
    return asyncio.get_running_loop().run_in_executor(None, fn, *args)


def offloaded(offload: Offload | None, commit: Callable[..., Seen], *args: Any) -> Awaitable[Seen]:
    """``commit_async`` of a store whose ``commit`` blocks: ``commit(*args)`` in a thread."""
    result: Awaitable[Seen] = (offload or in_executor)(commit, *args)
    return result


@runtime_checkable
class ReplayStore(Protocol):
    """Atomic replay state; see the module docstring for the contract."""

    @property
    def backend(self) -> str:
        """``memory``, ``sqlite``, ``redis`` or ``redis-cluster`` (a metrics label)."""

    def lookup(self, key: str) -> Seen: ...

    def fence(self) -> float:
        """The fence as last known to this process (no I/O)."""

    def watermark(self) -> float:
        """The watermark as last known to this process (no I/O)."""

    def commit(self, key: str, expires_at: float, now: float, force: bool = False) -> Seen: ...

    def commit_async(
        self,
        key: str,
        expires_at: float,
        now: float,
        force: bool = False,
        offload: Offload | None = None,
    ) -> Awaitable[Seen]:
        """:meth:`commit` from a running event loop (a blocking one runs in ``offload``)."""

    def verify(self) -> Seen:
        """Run this backend's loss detection now; the fence and watermark it finds."""

    def advance(self, key: str, value: int) -> bool: ...

    def advance_above(self, key: str, value: int, fence_key: str) -> bool:
        """:meth:`advance`, refused too unless ``value`` is above counter ``fence_key`` (if
        set), in the same atomic step: a counter another process just dropped under that
        fence (:meth:`forget`) cannot be advanced again from nothing."""

    def current(self, key: str) -> int | None: ...

    def forget(self, keys: Sequence[str], fence_key: str, fence: int) -> None:
        """Atomically advance counter ``fence_key`` to at least ``fence`` and delete the counters ``keys`` (missing ones are no-ops), with the same loss detection as ``advance``; forgetting never re-opens a replay because the fence covers what was dropped."""  # noqa: E501

    def status(self) -> dict[str, float]: ...

    def ready(self) -> None:
        """Raise ``StateUnavailableError`` unless a commit could go through now; records nothing."""

    def close(self) -> None: ...
