"""Refusals on the record at a bounded rate, the rest summarised: one auditor for every adapter.

Theory of operation
-------------------
Every refusal is counted by its adapter; :class:`RefusalAuditor` decides which of them
also get a row of their own (and a log line), so that a flood of hostile input cannot
grow the trail, its fsyncs or the log without bound, and writes the rest as **summary
rows**, so that an attack is fully counted on the record.

A refusal gets its own row when two budgets allow it: its class's token bucket
(:class:`~antireplay.core.ratelimit.TokenBucket`; *authenticated* refusals, the sender
verified, apart from *unauthenticated* ones, which anybody can send at line rate, so a
forged flood never starves the record of authentic refusals), and its key's share of
the interval: at most ``per_key`` rows per ``(class, cause, sender)`` per ``flush_s``,
so one noisy sender does not starve the others of their class.  A refusal left out is
*folded* into its key's tally (count, first and last time, its msg_id while they all
share one).  The table of keys is bounded (``max_keys``): a sender beyond it folds into
its class's and cause's "other senders" tally, so spraying senders grows nothing.  An
unauthenticated refusal's sender is only claimed, so that class gets at most
``unverified_keys`` senders of its own per interval: a flood spraying claimed senders
costs a handful of summary rows per cause, not one per name.

Every ``flush_s`` (checked as refusals arrive, by the adapter's timer, and at
``close``) each tally becomes one summary row: ``outcome`` ``summary``, the cause as
``code``, the sender and msg_id (``None`` if they differed), ``sender_verified`` its
class, the time of the last refusal folded, and ``warning`` ``folded=N first=T1
last=T2`` (:func:`summary_count` reads it back).  Rows, summaries and the refusals no
summary could record (:attr:`RefusalAuditor.unrecorded`: the trail failed, or free
space was below its floor, ``quiet``) add up to every refusal counted.

Accepted messages never pass through here: each keeps its own row.  A trail that cannot
take a refusal's own row raises ``STATE_UNAVAILABLE`` to the caller, which counts it.
"""

from __future__ import annotations

import logging
import re
import threading
from collections import Counter
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Protocol

from antireplay.audit.chain import AuditRow, sanitize
from antireplay.core.clock import Clock, resolve
from antireplay.core.ratelimit import TokenBucket

#: Audit rows (and log lines) per second, per class, unless an adapter says otherwise.
AUDIT_PER_S = 50.0
#: Seconds between summary flushes.
FLUSH_S = 10.0
#: Senders tallied apart, per auditor; the rest share their cause's "other senders" tally.
MAX_KEYS = 1024
#: Claimed (unverified) senders tallied apart per interval; the rest are "other senders".
UNVERIFIED_KEYS = 8
#: The key under which folded refusals are counted in an adapter's counter.
FOLDED = "audit_rate_limited"
#: The ``outcome`` of a summary row.
SUMMARY = "summary"
_COUNT = re.compile(r"folded=([0-9]+)")


class Trail(Protocol):
    """What the auditor writes to (:class:`~antireplay.audit.AuditLog`)."""

    def append(self, row: AuditRow) -> int: ...


def _class(authentic: bool) -> str:
    return "authenticated" if authentic else "unauthenticated"


def summary_count(outcome: str, warning: str | None) -> int:
    """How many refusals a row stands for: a summary's ``folded=N``, else 1."""
    if outcome != SUMMARY or warning is None:
        return 1
    found = _COUNT.match(warning)
    return int(found.group(1)) if found else 1


class _Other:
    """The sender of an "other senders" tally (never equal to a sender's string)."""


_OTHER = _Other()
Key = tuple[bool, str, "str | _Other | None"]


@dataclass(slots=True)
class _Tally:
    """Refusals of one key this interval: rows given, and what was folded."""

    rows: int = 0
    folded: int = 0
    first: float = 0.0
    last: float = 0.0
    msg_id: str | None = None
    mixed: bool = False

    def fold(self, at: float, msg_id: str | None) -> None:
        if not self.folded:
            self.first, self.msg_id = at, msg_id
        elif msg_id != self.msg_id:
            self.mixed = True
        self.folded += 1
        self.last = at


class RefusalAuditor:
    """Rate-limited rows and log lines for refusals, the rest summarised (module docstring)."""

    def __init__(
        self,
        audit: Trail | None = None,
        clock: Clock | None = None,
        *,
        per_s: float = AUDIT_PER_S,
        authentic_per_s: float | None = None,
        per_key: int | None = None,
        flush_s: float = FLUSH_S,
        max_keys: int = MAX_KEYS,
        unverified_keys: int = UNVERIFIED_KEYS,
        log: logging.Logger | None = None,
        counts: Counter[str] | None = None,
        quiet: Callable[[], bool] | None = None,
    ) -> None:
        self.audit, self.log = audit, log
        self.clock = resolve(clock)
        #: Refusals left off the record as rows of their own, per class.
        self.folded: Counter[str] = Counter()
        #: Folded refusals written as summary rows, and the summary rows.
        self.summarised = 0
        self.summaries = 0
        #: Folded refusals no summary recorded (the trail failed, or free space was low).
        self.unrecorded = 0
        rates = {False: per_s, True: per_s if authentic_per_s is None else authentic_per_s}
        #: Rows of their own per key and interval, per class (one second's budget by default).
        self.per_key = {a: max(1, int(r)) if per_key is None else per_key for a, r in rates.items()}
        self.flush_s, self.max_keys, self.unverified_keys = flush_s, max_keys, unverified_keys
        self._unverified = 0  # unauthenticated senders tallied apart this interval
        #: ``True`` while rows must not be written (free space below the first floor).
        self.quiet = quiet or (lambda: False)
        self._counts = counts
        self._budget = {a: TokenBucket(r, self.clock) for a, r in rates.items()}
        self._unlogged: Counter[str] = Counter()
        self._tallies: dict[Key, _Tally] = {}
        self._flushed = self.clock.monotonic()
        self._lock = threading.Lock()

    def admit(
        self,
        *,
        authentic: bool,
        code: str | None = None,
        sender: str | None = None,
        msg_id: object = None,
    ) -> bool:
        """Whether this refusal gets a row of its own; else it is folded into its tally
        (and counted).  Flushes the summaries first once ``flush_s`` has passed."""
        if self.clock.monotonic() - self._flushed >= self.flush_s:
            self.flush()
        quiet = self.quiet()
        with self._lock:
            tally = self._tally((authentic, str(code), sender))
            room = not quiet and tally.rows < self.per_key[authentic]
            if room and self._budget[authentic].take():
                tally.rows += 1
                return True
            tally.fold(self.clock.wall(), sanitize(msg_id))
            self.folded[_class(authentic)] += 1
            self._unlogged[_class(authentic)] += 1
            if self._counts is not None:
                self._counts[FOLDED] += 1
        return False

    def _tally(self, key: Key) -> _Tally:
        """The key's tally (the caller holds the lock); beyond ``max_keys``, or for an
        unauthenticated sender beyond ``unverified_keys``, its cause's "other senders"
        tally."""
        tally = self._tallies.get(key)
        if tally is None:
            full = len(self._tallies) >= self.max_keys
            if full or (not key[0] and self._unverified >= self.unverified_keys):
                key = (key[0], key[1], _OTHER)
                tally = self._tallies.get(key)
            elif not key[0]:
                self._unverified += 1
            if tally is None:
                tally = self._tallies[key] = _Tally()
        return tally

    def record(
        self,
        *,
        code: str,
        sender: str | None,
        sender_verified: bool,
        warning: str | None = None,
        msg_id: str | None = None,
        line: str | None = None,
    ) -> bool:
        """One row (and, with a logger, ``line`` as a warning) unless the budgets are spent;
        ``True`` if it was recorded.  Raises ``STATE_UNAVAILABLE`` from the trail."""
        if not self.admit(authentic=sender_verified, code=code, sender=sender, msg_id=msg_id):
            return False
        if self.log is not None and line is not None:
            with self._lock:
                left_out = self._unlogged.pop(_class(sender_verified), 0)
            more = f" ({left_out} more refusals not logged)" if left_out else ""
            self.log.warning("%s%s", line, more)
        if self.audit is not None:
            self.audit.append(
                AuditRow(self.clock.wall(), "rejected", code, warning, sender=sender,
                         sender_verified=sender_verified, msg_id=msg_id)
            )  # fmt: skip
        return True

    def flush(self) -> int:
        """Write the interval's tallies as summary rows (queued on the trail's next group
        commit when it has one, not awaited) and start a new interval; returns the rows
        queued.  Below the free-space floor nothing is written, only counted."""
        with self._lock:
            tallies, self._tallies = self._tallies, {}
            self._unverified = 0
            self._flushed = self.clock.monotonic()
        rows = [(key, t) for key, t in tallies.items() if t.folded]
        if not rows:
            return 0
        if self.audit is None or self.quiet():
            with self._lock:
                self.unrecorded += sum(t.folded for _, t in rows)
            return 0
        for (authentic, code, sender), tally in rows:
            self._write(self._summary(authentic, code, sender, tally), tally.folded)
        return len(rows)

    @staticmethod
    def _summary(
        authentic: bool, code: str, sender: str | _Other | None, tally: _Tally
    ) -> AuditRow:
        other = isinstance(sender, _Other)
        warning = f"folded={tally.folded} first={tally.first:.3f} last={tally.last:.3f}"
        warning += " senders=other" if other else ""
        warning += " msg_ids=various" if tally.mixed else ""
        who = None if isinstance(sender, _Other) else sender
        return AuditRow(
            tally.last, SUMMARY, code, warning, sender=who, sender_verified=authentic,
            msg_id=None if tally.mixed else tally.msg_id,
        )  # fmt: skip

    def _write(self, row: AuditRow, folded: int) -> None:
        """Queue one summary row; what it stands for is counted once it is durable."""
        later = getattr(self.audit, "append_later", None)
        done: Future[int]
        try:
            if later is not None:
                done = later(row)
            else:
                assert self.audit is not None
                done = Future()
                done.set_result(self.audit.append(row))
        except Exception:  # a closed or failing trail: counted, never raised
            done = Future()
            done.set_exception(RuntimeError("audit trail unavailable"))
        done.add_done_callback(lambda f: self._written(f, folded))

    def _written(self, done: Future[int], folded: int) -> None:
        with self._lock:
            if done.exception() is None:
                self.summaries += 1
                self.summarised += folded
            else:
                self.unrecorded += folded
        if done.exception() is not None and self.log is not None:
            self.log.error("audit trail unavailable: a summary of %d refusals lost", folded)

    def close(self) -> None:
        """Flush what is tallied (call before the trail closes)."""
        self.flush()

    @property
    def folded_total(self) -> int:
        """Every refusal left off the record as a row of its own, both classes."""
        return sum(self.folded.values())

    @property
    def pending(self) -> int:
        """Folded refusals not flushed yet."""
        with self._lock:
            return sum(t.folded for t in self._tallies.values())


__all__ = [
    "AUDIT_PER_S",
    "FLUSH_S",
    "FOLDED",
    "MAX_KEYS",
    "SUMMARY",
    "UNVERIFIED_KEYS",
    "RefusalAuditor",
    "Trail",
    "summary_count",
]
