"""Refusals on the record at a bounded rate: one auditor for every adapter.

Theory of operation
-------------------
Every refusal is counted by its adapter; :class:`RefusalAuditor` decides which
of them also get an audit row (and a log line), so that a flood of hostile
input cannot grow the trail, its fsyncs or the log without bound.  It keeps
two token buckets (:class:`~antireplay.core.ratelimit.TokenBucket`), one per
class of refusal:

* **authenticated**: the sender was verified (a replayed or stale message
  under a genuine signature), the refusals an operator must see;
* **unauthenticated**: malformed, forged or unknown-sender input, which anybody
  can send at line rate.

A flood of forged packets empties only the unauthenticated budget, so the
record of authentic refusals is never starved.  A refusal left out is
*folded*: counted per class in :attr:`RefusalAuditor.folded` (and under
``audit_rate_limited`` in the adapter's counter, when it passes one), so the
metrics and the trail add up to the same total.  The next log line of a class
says how many of its refusals were folded since the previous one.

Accepted messages never pass through here: each keeps its own row.  A trail
that cannot take a row raises ``STATE_UNAVAILABLE`` to the caller, which
counts it (the refusal stands either way).
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from typing import Protocol

from antireplay.core.clock import Clock, resolve
from antireplay.core.ratelimit import TokenBucket

#: Audit rows (and log lines) per second, per class, unless an adapter says otherwise.
AUDIT_PER_S = 50.0
#: The key under which folded refusals are counted in an adapter's counter.
FOLDED = "audit_rate_limited"


class Trail(Protocol):
    """What the auditor writes to (:class:`~antireplay.audit.AuditLog`)."""

    def append(
        self,
        *,
        at: float,
        outcome: str,
        code: str | None,
        warning: str | None,
        msg_type: int | None,
        sender: object,
        sender_verified: bool,
        msg_id: object,
    ) -> int: ...


def _class(authentic: bool) -> str:
    return "authenticated" if authentic else "unauthenticated"


class RefusalAuditor:
    """Rate-limited audit rows and log lines for refusals, one budget per class."""

    def __init__(
        self,
        audit: Trail | None = None,
        clock: Clock | None = None,
        *,
        per_s: float = AUDIT_PER_S,
        log: logging.Logger | None = None,
        counts: Counter[str] | None = None,
    ) -> None:
        self.audit, self.log = audit, log
        self.clock = resolve(clock)
        #: Refusals left off the record, per class (``authenticated``/``unauthenticated``).
        self.folded: Counter[str] = Counter()
        self._counts = counts
        self._budget = {a: TokenBucket(per_s, self.clock) for a in (False, True)}
        self._unlogged: Counter[str] = Counter()
        self._lock = threading.Lock()

    def admit(self, *, authentic: bool) -> bool:
        """Take a token from the refusal's class; ``False`` (and counted) when it is spent."""
        if self._budget[authentic].take():
            return True
        with self._lock:
            self.folded[_class(authentic)] += 1
            self._unlogged[_class(authentic)] += 1
            if self._counts is not None:
                self._counts[FOLDED] += 1
        return False

    def record(
        self,
        *,
        code: str,
        sender: object,
        sender_verified: bool,
        warning: str | None = None,
        msg_id: object = None,
        line: str | None = None,
    ) -> bool:
        """One row (and, with a logger, ``line`` as a warning) unless the class's budget is
        spent; ``True`` if it was recorded.  Raises ``STATE_UNAVAILABLE`` from the trail."""
        if not self.admit(authentic=sender_verified):
            return False
        if self.log is not None and line is not None:
            with self._lock:
                left_out = self._unlogged.pop(_class(sender_verified), 0)
            more = f" ({left_out} more refusals not logged)" if left_out else ""
            self.log.warning("%s%s", line, more)
        if self.audit is not None:
            self.audit.append(
                at=self.clock.wall(), outcome="rejected", code=code, warning=warning,
                msg_type=None, sender=sender, sender_verified=sender_verified, msg_id=msg_id,
            )  # fmt: skip
        return True

    @property
    def folded_total(self) -> int:
        """Every refusal left off the record, both classes."""
        return sum(self.folded.values())


__all__ = ["AUDIT_PER_S", "FOLDED", "RefusalAuditor", "Trail"]
