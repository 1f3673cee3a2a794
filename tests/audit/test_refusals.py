"""The one rate-limited refusal auditor: a budget per class, every fold counted."""

from __future__ import annotations

import logging
from collections import Counter
from pathlib import Path

import pytest

from antireplay.audit import AuditLog, RefusalAuditor
from antireplay.audit.refusals import FOLDED
from antireplay.core.clock import ManualClock
from antireplay.core.errors import StateUnavailableError

RATE = 5


def _forged(auditor: RefusalAuditor, n: int) -> None:
    for _ in range(n):
        auditor.record(code="SIGNATURE_INVALID", sender="mallory", sender_verified=False)


def test_each_class_has_its_own_budget(tmp_path: Path) -> None:
    clock = ManualClock()
    audit = AuditLog(tmp_path / "audit.db")
    auditor = RefusalAuditor(audit, clock, per_s=RATE)
    try:
        _forged(auditor, 3 * RATE)
        authentic = [
            auditor.record(code="REPLAY_DETECTED", sender="alice", sender_verified=True)
            for _ in range(2 * RATE)
        ]
        assert authentic == [True] * RATE + [False] * RATE
        assert auditor.folded == Counter(unauthenticated=2 * RATE, authenticated=RATE)
        assert audit.count() == 2 * RATE
    finally:
        audit.close()


def test_authentic_refusals_are_recorded_under_a_forged_flood(tmp_path: Path) -> None:
    clock = ManualClock()
    audit = AuditLog(tmp_path / "audit.db")
    auditor = RefusalAuditor(audit, clock, per_s=RATE)
    try:
        for _ in range(3):  # a flood that never stops, and one replay between its waves
            _forged(auditor, 100)
            assert auditor.record(code="REPLAY_DETECTED", sender="alice", sender_verified=True)
            clock.advance(1.0)
        verified = [r for r in audit.tail(1_000) if r.sender_verified]
        assert [(r.code, r.sender) for r in verified] == [("REPLAY_DETECTED", "alice")] * 3
        assert auditor.folded["authenticated"] == 0
    finally:
        audit.close()


def test_folded_counts_and_records_add_up_to_every_refusal(tmp_path: Path) -> None:
    clock = ManualClock()
    audit = AuditLog(tmp_path / "audit.db")
    counts: Counter[str] = Counter()
    auditor = RefusalAuditor(audit, clock, per_s=RATE, counts=counts)
    refusals = 0
    try:
        for wave in range(4):
            _forged(auditor, 7 * wave)
            refusals += 7 * wave
            clock.advance(0.5)
        assert audit.count() + auditor.folded_total == refusals
        assert counts[FOLDED] == auditor.folded_total > 0
    finally:
        audit.close()


def test_the_budget_comes_back_with_time() -> None:
    clock = ManualClock()
    auditor = RefusalAuditor(clock=clock, per_s=RATE)
    assert [auditor.admit(authentic=False) for _ in range(RATE + 1)][-2:] == [True, False]
    clock.advance(1.0 / RATE)
    assert auditor.admit(authentic=False)
    assert not auditor.admit(authentic=False)


def test_the_next_log_line_says_how_many_were_folded(caplog: pytest.LogCaptureFixture) -> None:
    clock = ManualClock()
    auditor = RefusalAuditor(clock=clock, per_s=1, log=logging.getLogger("test.refusals"))
    with caplog.at_level(logging.WARNING, logger="test.refusals"):
        for n in range(4):
            auditor.record(code="X", sender=None, sender_verified=False, line=f"refused {n}")
        clock.advance(1.0)
        auditor.record(code="X", sender=None, sender_verified=False, line="refused again")
    assert caplog.messages == ["refused 0", "refused again (3 more refusals not logged)"]


class _DownTrail:
    def append(self, **_: object) -> int:
        raise StateUnavailableError("audit trail unavailable: disk full")


def test_a_trail_that_is_down_is_the_callers_to_count() -> None:
    auditor = RefusalAuditor(_DownTrail(), ManualClock(), per_s=RATE)
    with pytest.raises(StateUnavailableError):
        auditor.record(code="SIGNATURE_INVALID", sender=None, sender_verified=False)
    assert auditor.folded_total == 0
