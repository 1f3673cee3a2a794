"""``antireplay audit tail`` and ``audit verify`` on what a trail holds: free-text reasons
shown escaped and bounded, tampered values shown invalid and named by verify, rows read
across segments."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from antireplay.audit import AuditLog, AuditRow, verify
from antireplay.audit.segments import rotated
from antireplay.cli import main
from harness.audit import segmented, sql, trail

REASON = "database missing, truncated or replaced (the witness says it existed)"


def lost_and_found(path: Path, reason: str) -> None:
    """A STATE_LOST row (its warning is the store's reason, free text) and a row with no
    sender (a memo hit)."""
    log = AuditLog(path)
    log.append(AuditRow(at=1_800_000_000.0, outcome="state", code="STATE_LOST", warning=reason))
    log.append(AuditRow(at=1_800_000_001.0, outcome="rejected", code="REPLAY_DETECTED",
                        msg_type=1, msg_id="m1"))  # fmt: skip
    log.close()


def tail_json(path: Path) -> list[dict[str, Any]]:
    result = CliRunner().invoke(main, ["audit", "tail", str(path), "--json"])
    assert result.exit_code == 0, result.output
    return [json.loads(line) for line in result.output.splitlines()]


def test_audit_tail_shows_the_state_lost_reason_and_no_none_sender(tmp_path: Path) -> None:
    path = tmp_path / "audit.db"
    lost_and_found(path, REASON)
    lost, memo = tail_json(path)
    assert lost["warning"] == REASON
    table = CliRunner().invoke(main, ["audit", "tail", str(path)])
    assert table.exit_code == 0, table.output
    assert REASON in table.output
    assert "None" not in table.output  # a row without a sender shows "-"
    assert memo["sender"] is None


def test_audit_tail_escapes_and_bounds_a_hostile_reason(tmp_path: Path) -> None:
    path = tmp_path / "audit.db"
    lost_and_found(path, "lost\x1b[2J\nforged line\u202e" + "x" * 500)
    (lost, _) = tail_json(path)
    shown = lost["warning"]
    assert shown.startswith("lost\\x1b[2J\\nforged line\\u202e") and len(shown) == 200
    assert shown.isprintable()
    table = CliRunner().invoke(main, ["audit", "tail", str(path)])
    assert "\x1b" not in table.output and "forged line" in table.output


@pytest.mark.parametrize("at", ["1e300", "9e999", "-9e999", "-5", "'yesterday'", "x'00'"])
def test_a_tampered_time_or_type_is_shown_invalid_and_verify_names_the_row(
    tmp_path: Path, at: str
) -> None:
    path = tmp_path / "audit.db"
    trail(path, 3)
    sql(path, f"UPDATE audit SET at = {at}, msg_type = 'x\x1b[31m<b>' || char(10) WHERE seq = 2")
    for args in (["--json"], []):
        result = CliRunner().invoke(main, ["audit", "tail", str(path), *args])
        assert result.exit_code == 0, result.output
        assert "Traceback" not in result.output and "\x1b" not in result.output
        assert "<b>" not in result.output  # the hostile type is hashed like any identifier
    rows = tail_json(path)
    assert (rows[1]["at"], rows[1]["time"]) == (None, "invalid")
    assert rows[1]["msg_type"].startswith("sha256:")
    assert rows[0]["time"] == "2027-01-15T08:00:00Z"  # its neighbours are intact
    report = verify(path)
    assert (report.broken_at, report.reason) == (2, "invalid at: a value antireplay never writes")
    result = CliRunner().invoke(main, ["audit", "verify", str(path)])
    assert result.exit_code == 1 and "chain broken at row 2: invalid at" in result.output


def test_verify_names_a_blob_in_a_text_column(tmp_path: Path) -> None:
    path = tmp_path / "audit.db"
    trail(path, 2)
    sql(path, "UPDATE audit SET sender = x'ff00' WHERE seq = 1")
    assert (verify(path).broken_at, verify(path).reason) == (
        1, "invalid sender: a value antireplay never writes",
    )  # fmt: skip
    assert CliRunner().invoke(main, ["audit", "tail", str(path)]).exit_code == 0


def test_audit_tail_and_verify_read_across_segments(tmp_path: Path) -> None:
    """``audit tail -n 60`` spans rotated segments in order; ``audit verify`` counts them."""
    path = tmp_path / "audit.db"
    segmented(path, 140).close()
    assert len(rotated(path)) >= 3
    rows = [json.loads(line) for line in CliRunner().invoke(
        main, ["audit", "tail", str(path), "-n", "60", "--json"]
    ).output.splitlines()]  # fmt: skip
    assert [row["seq"] for row in rows] == list(range(81, 141))
    assert [row["msg_id"] for row in rows] == [f"m{i}" for i in range(80, 140)]
    table = CliRunner().invoke(main, ["audit", "tail", str(path), "-n", "60"])
    assert table.exit_code == 0 and "m80" in table.output and "m139" in table.output
    said = CliRunner().invoke(main, ["audit", "verify", str(path)])
    segments = len(rotated(path)) + 1
    assert said.exit_code == 0
    assert f"chain intact to row 140 (140 records in {segments} segments)" in said.output
