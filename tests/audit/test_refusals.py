"""The one rate-limited refusal auditor: a budget per class and per sender, every fold
counted and summarised."""

from __future__ import annotations

import logging
from collections import Counter
from pathlib import Path

import pytest

from antireplay.audit import AuditLog, AuditRow, RefusalAuditor
from antireplay.audit.refusals import FOLDED, SUMMARY, UNVERIFIED_KEYS, summary_count
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
    auditor = RefusalAuditor(clock=clock, per_s=RATE, per_key=100)
    assert [auditor.admit(authentic=False) for _ in range(RATE + 1)][-2:] == [True, False]
    clock.advance(1.0 / RATE)
    assert auditor.admit(authentic=False)
    assert not auditor.admit(authentic=False)


def test_the_next_log_line_says_how_many_were_folded(caplog: pytest.LogCaptureFixture) -> None:
    clock = ManualClock()
    auditor = RefusalAuditor(
        clock=clock, per_s=1, per_key=100, log=logging.getLogger("test.refusals")
    )
    with caplog.at_level(logging.WARNING, logger="test.refusals"):
        for n in range(4):
            auditor.record(code="X", sender=None, sender_verified=False, line=f"refused {n}")
        clock.advance(1.0)
        auditor.record(code="X", sender=None, sender_verified=False, line="refused again")
    assert caplog.messages == ["refused 0", "refused again (3 more refusals not logged)"]


class _DownTrail:
    def append(self, row: AuditRow) -> int:
        raise StateUnavailableError("audit trail unavailable: disk full")


def test_a_trail_that_is_down_is_the_callers_to_count() -> None:
    auditor = RefusalAuditor(_DownTrail(), ManualClock(), per_s=RATE)
    with pytest.raises(StateUnavailableError):
        auditor.record(code="SIGNATURE_INVALID", sender=None, sender_verified=False)
    assert auditor.folded_total == 0


def _counted(audit: AuditLog) -> int:
    """Refusals the trail stands for: one per row, a summary's ``folded=N`` for it."""
    return sum(summary_count(r.outcome, r.warning) for r in audit.tail(100_000))


def test_rows_and_summaries_add_up_to_every_refusal_of_mixed_causes_and_senders(
    tmp_path: Path,
) -> None:
    clock = ManualClock()
    audit = AuditLog(tmp_path / "audit.db")
    auditor = RefusalAuditor(audit, clock, per_s=RATE, flush_s=10.0)
    causes = ("REPLAY_DETECTED", "SIGNATURE_INVALID", "TIMESTAMP_STALE")
    n = 0
    try:
        for second in range(25):  # two flush intervals and a half
            for i in range(40):
                auditor.record(
                    code=causes[i % 3], sender=f"s{i % 7}", sender_verified=i % 2 == 0,
                    msg_id=f"m{i % 5}",
                )  # fmt: skip
                n += 1
            clock.advance(1.0)
            assert second < 20 or auditor.pending  # the last interval is not flushed yet
        auditor.close()
        audit.close()
        audit = AuditLog(tmp_path / "audit.db")
        summaries = [r for r in audit.tail(100_000) if r.outcome == SUMMARY]
        assert summaries and all(r.code in causes for r in summaries)
        assert _counted(audit) == n == audit.count() - len(summaries) + auditor.summarised
        assert auditor.folded_total == auditor.summarised and auditor.unrecorded == 0
    finally:
        audit.close()


def test_one_summary_row_names_its_cause_sender_and_msg_id(tmp_path: Path) -> None:
    clock = ManualClock(1_700_000_000.0)
    audit = AuditLog(tmp_path / "audit.db")
    auditor = RefusalAuditor(audit, clock, per_s=RATE, flush_s=10.0)
    try:
        for _ in range(RATE + 12):
            auditor.record(code="REPLAY_DETECTED", sender="owner-y", sender_verified=False,
                           msg_id="msg-x")  # fmt: skip
            clock.advance(0.1)
        clock.advance(10.0)
        auditor.record(code="REPLAY_DETECTED", sender="owner-y", sender_verified=False,
                       msg_id="msg-z")  # fmt: skip  # the interval is over: flushed first
        audit.close()
        audit = AuditLog(tmp_path / "audit.db")
        [summary] = [r for r in audit.tail(100) if r.outcome == SUMMARY]
        assert (summary.code, summary.sender, summary.msg_id) == (
            "REPLAY_DETECTED", "owner-y", "msg-x",
        )  # fmt: skip
        assert summary.warning == "folded=12 first=1700000000.500 last=1700000001.600"
        assert not summary.sender_verified and summary.at == pytest.approx(1_700_000_001.6)
    finally:
        audit.close()


def test_a_noisy_sender_does_not_starve_the_others_of_its_class() -> None:
    clock = ManualClock()
    auditor = RefusalAuditor(clock=clock, per_s=RATE * 10, per_key=RATE)
    noisy = [auditor.admit(authentic=False, code="X", sender="noisy") for _ in range(100)]
    quiet = auditor.admit(authentic=False, code="X", sender="quiet")
    assert sum(noisy) == RATE and quiet


def test_sprayed_senders_fold_into_one_other_senders_tally(tmp_path: Path) -> None:
    """An attacker claiming a new sender each time grows no table: beyond ``max_keys`` they
    share one tally per class and cause, written as one row saying ``senders=other``."""
    clock = ManualClock()
    audit = AuditLog(tmp_path / "audit.db")
    auditor = RefusalAuditor(audit, clock, per_s=RATE, max_keys=8)
    try:
        for i in range(5_000):
            auditor.record(code="SIGNATURE_INVALID", sender=f"spoof-{i}", sender_verified=False)
        assert len(auditor._tallies) == 9  # eight senders and the other senders
        auditor.close()
        audit.close()
        audit = AuditLog(tmp_path / "audit.db")
        others = [r for r in audit.tail(100) if r.warning and "senders=other" in r.warning]
        assert len(others) == 1 and others[0].sender is None
        assert summary_count(others[0].outcome, others[0].warning) == 5_000 - 8
        assert _counted(audit) == 5_000
    finally:
        audit.close()


def test_claimed_senders_of_unauthenticated_refusals_cost_a_handful_of_summaries(
    tmp_path: Path,
) -> None:
    """Bad signatures under a new claimed sender each (the default ``max_keys``): per cause
    and interval at most ``UNVERIFIED_KEYS`` senders are summarised apart, the rest in one
    "other senders" row; authenticated senders keep a tally each; all counted."""
    clock = ManualClock()
    audit = AuditLog(tmp_path / "audit.db")
    auditor = RefusalAuditor(audit, clock, per_s=RATE)
    try:
        for interval in range(2):
            for i in range(1_000):
                auditor.record(code="SIGNATURE_INVALID", sender=f"spoof-{interval}-{i}",
                               sender_verified=False)  # fmt: skip
            for i in range(40):
                auditor.record(code="REPLAY_DETECTED", sender=f"op-{i % 20}",
                               sender_verified=True)  # fmt: skip
            clock.advance(10.0)
            auditor.flush()
        audit.close()
        audit = AuditLog(tmp_path / "audit.db")
        summaries = [r for r in audit.tail(100_000) if r.outcome == SUMMARY]
        forged = [r for r in summaries if not r.sender_verified]
        assert len(forged) <= 2 * (UNVERIFIED_KEYS + 1)  # was one per claimed sender
        assert sum("senders=other" in (r.warning or "") for r in forged) == 2
        assert len([r for r in summaries if r.sender_verified]) == 2 * 20  # one per sender
        assert _counted(audit) == 2 * 1_040 == audit.count() - len(summaries) + auditor.summarised
    finally:
        audit.close()


def test_mixed_msg_ids_are_summarised_without_one() -> None:
    clock = ManualClock()
    rows: list[AuditRow] = []

    class Trail:
        def append(self, row: AuditRow) -> int:
            rows.append(row)
            return len(rows)

    auditor = RefusalAuditor(Trail(), clock, per_s=1, per_key=1)
    for i in range(4):
        auditor.record(code="REPLAY_DETECTED", sender="a", sender_verified=True, msg_id=f"m{i}")
    auditor.flush()
    assert rows[-1].msg_id is None and "msg_ids=various" in str(rows[-1].warning)
    assert summary_count(SUMMARY, str(rows[-1].warning)) == 3


def test_below_the_floor_refusals_and_summaries_are_only_counted(tmp_path: Path) -> None:
    clock = ManualClock()
    audit = AuditLog(tmp_path / "audit.db")
    low = [False]
    auditor = RefusalAuditor(audit, clock, per_s=RATE, quiet=lambda: low[0])
    try:
        _forged(auditor, 2 * RATE)
        low[0] = True
        _forged(auditor, 30)
        auditor.flush()
        assert audit.count() == RATE  # rows before the floor; no summary below it
        assert auditor.unrecorded == RATE + 30 and auditor.summarised == 0
    finally:
        audit.close()


def test_a_summary_the_trail_cannot_take_is_counted_unrecorded() -> None:
    auditor = RefusalAuditor(_DownTrail(), ManualClock(), per_s=0.5)
    for _ in range(3):
        auditor.admit(authentic=False, code="SIGNATURE_INVALID")
    assert auditor.flush() == 1
    assert (auditor.unrecorded, auditor.summarised) == (3, 0)
