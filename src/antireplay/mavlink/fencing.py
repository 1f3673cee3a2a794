"""Refusals behind a restart fence, folded: the first said at once, the rest one line per interval.

Theory of operation
-------------------
A router that starts fenced (a memory store, a new or lost state, a clock spike the previous
run accepted) refuses every frame stamped before its fence, often hundreds a second.  Each is
still counted (the router's ``dropped`` counter), but only the first on a link and direction
is reported (a log line and an audit row); the rest are folded here and reported as one
summary per ``FENCE_SUMMARY_S``: how many frames, from how many claimed senders (unverified:
the fence is checked before the signature), and until when the fence holds.  A sender still
refused after the fence has passed by the router's clock stamps below it: its clock lags the
router's, or its frames are captures; its refusals keep folding, one line per interval that
says so.  A link quiet behind the fence for an interval after it has passed starts over (a
later fence, after a store loss, reports its first refusal again).  No I/O here: the router
reports what :meth:`FenceFolds.refused` and :meth:`FenceFolds.summaries` hand it; times come
in as arguments.
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
    below_s: float = 0.0  # the most seconds below the fence a folded frame stamped


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
        self,
        direction: str,
        link: str,
        code: str,
        sender: tuple[int, int],
        now: float,
        *,
        below_s: float = 0.0,
    ) -> bool:
        """Fold one refusal (``below_s`` below the fence); ``True`` if it is the first on
        this link (report it now)."""
        with self._lock:
            fold = self._folds.get((direction, link))
            if fold is None:
                self._folds[direction, link] = _Fold(code, now)
                return True
            fold.frames += 1
            fold.below_s = max(fold.below_s, below_s)
            if len(fold.senders) < self.max_senders:
                fold.senders.add(sender)
            return False

    def summaries(
        self, fence: Fence | None, wall: float, now: float, *, final: bool = False
    ) -> list[Summary]:
        """The lines due at monotonic ``now`` (every ``FENCE_SUMMARY_S``, all when
        ``final``, at stop); ``fence`` None: the fence has passed by the router's clock."""
        lines: list[Summary] = []
        with self._lock:
            for (direction, link), fold in list(self._folds.items()):
                due = final or now - fold.said >= FENCE_SUMMARY_S
                if fold.frames and due:
                    reason = (
                        f"behind the restart fence{until_text(fence, wall)}: "
                        f"{claimed(fold.senders)} in the last {now - fold.said:.0f} s"
                        if fence is not None
                        else lagging(fold.senders, fold.below_s)
                    )
                    lines.append(Summary(direction, link, fold.code, reason, fold.frames))
                    fold.frames, fold.senders, fold.said, fold.below_s = 0, set(), now, 0.0
                elif fence is None and due:  # quiet for an interval past the fence
                    del self._folds[direction, link]
        return lines


def claimed(senders: set[tuple[int, int]]) -> str:
    """``from N senders (claimed ids)``: the ids are unverified (checked before crypto)."""
    n = len(senders)
    return f"from {n} sender{'' if n == 1 else 's'} (claimed ids, not verified)"


def lagging(senders: set[tuple[int, int]], below_s: float) -> str:
    """Why frames are refused behind a fence that has passed by the router's clock."""
    if len(senders) == 1:
        system, component = next(iter(senders))
        return (
            f"sender {system}/{component}'s timestamps are {below_s:.1f} s below the restart "
            "fence, which has passed by this router's clock: its clock is behind, or these "
            "are captures"
        )
    return (
        f"{claimed(senders)}: timestamps up to {below_s:.1f} s below the restart fence, which "
        "has passed by this router's clock: their clocks are behind, or these are captures"
    )


def until_text(fence: Fence | None, wall: float) -> str:
    """`` until <UTC time> (<n> s more)`` for a fence still ahead at ``wall``, else ``""``."""
    if fence is None:
        return ""
    when = datetime.fromtimestamp(fence[0], timezone.utc).isoformat(timespec="seconds")
    return f" until {when} ({max(0.0, fence[0] - wall):.1f} s more)"
