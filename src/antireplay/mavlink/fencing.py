"""Refusals behind a restart fence, folded: the first said at once, the rest one line per interval.

Theory of operation
-------------------
A router that starts fenced (a memory store, a new or lost state, a clock spike the previous
run accepted) refuses every frame stamped before its fence, often hundreds a second.  Each is
still counted (the router's ``dropped`` counter), but only the first on a link and direction
is reported (a log line and an audit row); the rest are folded here and reported as one
summary per ``FENCE_SUMMARY_S``: how many frames, from how many claimed senders, and until
when the fence holds.  Once the fence has passed, what is left is reported at the next tick
and the link starts over (a later fence, after a store loss, reports its first refusal
again).  No I/O here: the router reports what :meth:`FenceFolds.refused` and
:meth:`FenceFolds.summaries` hand it; times come in as arguments.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from datetime import datetime, timezone

FENCE_SUMMARY_S = 5.0  # refusals behind a restart fence: one line per link this often
#: A fence still ahead: until when (wall seconds) and why (``lease``, ``high``, ``lost``).
Fence = tuple[float, str]


@dataclass
class _Fold:
    """Refusals behind the fence on one link, one direction, since its last line."""

    code: str
    said: float  # monotonic time of the last line
    frames: int = 0
    senders: set[tuple[int, int]] = field(default_factory=set)


@dataclass(frozen=True)
class Summary:
    """One line to report: ``frames`` refused on ``link`` in ``direction``, and why."""

    direction: str
    link: str
    code: str
    reason: str
    frames: int


class FenceFolds:
    """The folds of one router, per ``(direction, link)``; thread-safe."""

    def __init__(self, max_senders: int = 1024) -> None:
        self.max_senders = max_senders
        self._folds: dict[tuple[str, str], _Fold] = {}
        self._lock = threading.Lock()

    def refused(
        self, direction: str, link: str, code: str, sender: tuple[int, int], now: float
    ) -> bool:
        """Fold one refusal; ``True`` if it is the first on this link (report it now)."""
        with self._lock:
            fold = self._folds.get((direction, link))
            if fold is None:
                self._folds[direction, link] = _Fold(code, now)
                return True
            fold.frames += 1
            if len(fold.senders) < self.max_senders:
                fold.senders.add(sender)
            return False

    def summaries(
        self, fence: Fence | None, wall: float, now: float, *, final: bool = False
    ) -> list[Summary]:
        """The lines due at monotonic ``now`` (every ``FENCE_SUMMARY_S``; all of them once
        the fence has passed or when ``final``, at stop)."""
        lines: list[Summary] = []
        with self._lock:
            for (direction, link), fold in list(self._folds.items()):
                if fold.frames and (final or fence is None or now - fold.said >= FENCE_SUMMARY_S):
                    n = len(fold.senders)
                    reason = (
                        f"behind the restart fence{until_text(fence, wall)}: from {n} "
                        f"sender{'' if n == 1 else 's'} in the last {now - fold.said:.0f} s"
                    )
                    lines.append(Summary(direction, link, fold.code, reason, fold.frames))
                    fold.frames, fold.senders, fold.said = 0, set(), now
                if fence is None and not fold.frames:
                    del self._folds[direction, link]
        return lines


def until_text(fence: Fence | None, wall: float) -> str:
    """`` until <UTC time> (<n> s more)`` for a fence still ahead at ``wall``, else ``""``."""
    if fence is None:
        return ""
    when = datetime.fromtimestamp(fence[0], timezone.utc).isoformat(timespec="seconds")
    return f" until {when} ({max(0.0, fence[0] - wall):.1f} s more)"
