"""Consistency: the trail against a head recorded elsewhere (the state database, an export).
A rollback, a truncation, a rewrite and a replaced trail fail; a head retention removed is
reported as not comparable, with what is proven; the writer records its head with each
fsynced drain and says ``AUDIT_ROLLED_BACK`` when it attaches behind the record."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from antireplay.audit import AuditLog, AuditRow, Retention, export_head, verify
from antireplay.audit.consistency import ROLLED_BACK
from antireplay.cli import main
from antireplay.core.clock import ManualClock
from antireplay.core.errors import AuditFileError
from antireplay.state.outbox import read_trail_head
from antireplay.state.sqlite import SqliteStore
from harness.audit import SMALL_SEGMENT, append, segmented, sql, trail


def _put(audit: AuditLog, i: int) -> None:
    audit.append(AuditRow(
        at=1_800_000_000.0 + i, outcome="accepted", code=None, warning=None, msg_type=1,
        sender="op", sender_verified=True, msg_id=f"m{i}",
    ))  # fmt: skip


def _gateway(where: Path, rows: range) -> None:
    """A store and its trail, ``rows`` accepted through the outbox, then closed."""
    store = SqliteStore(where / "state.db")
    audit = AuditLog(where / "audit.db", clock=ManualClock())
    audit.attach(store.outbox())
    for i in rows:
        _put(audit, i)
    audit.close()
    store.close()


def _copy_trail(where: Path, to: Path) -> None:
    to.mkdir()
    for file in where.glob("audit.db*"):
        shutil.copy2(file, to / file.name)


def _restore_trail(copy: Path, where: Path) -> None:
    for file in where.glob("audit.db*"):
        file.unlink()
    for file in copy.iterdir():
        shutil.copy2(file, where / file.name)


def test_each_fsynced_drain_records_the_head_in_the_state_database(tmp_path: Path) -> None:
    _gateway(tmp_path, range(3))
    recorded = read_trail_head(tmp_path / "state.db")
    assert recorded is not None and recorded[0] == 3
    report = verify(tmp_path / "audit.db", state=tmp_path / "state.db")
    assert report.ok and report.state is not None and report.state.ok
    assert "state database at row 3: the chain extends it (MAC verified)" in report.lines()


def test_a_trail_put_back_behind_the_record_is_rolled_back_at_attach(tmp_path: Path) -> None:
    _gateway(tmp_path, range(3))
    _copy_trail(tmp_path, tmp_path / "copy")
    _gateway(tmp_path, range(3, 4))
    _restore_trail(tmp_path / "copy", tmp_path)
    report = verify(tmp_path / "audit.db", state=tmp_path / "state.db")
    assert not report.ok and report.state is not None
    assert report.state.problem == (
        f"rolled back: row 4 (hash {report.state.head.hash[:16]}…) was recorded, "
        "the trail ends at row 3"
    )
    store = SqliteStore(tmp_path / "state.db")
    audit = AuditLog(tmp_path / "audit.db", clock=ManualClock())
    audit.attach(store.outbox())
    assert audit.rollbacks == 1 and audit.rolled_back is not None
    assert audit.rolled_back.startswith("behind the state database")
    assert [r.code for r in audit.tail(1)] == [ROLLED_BACK]
    audit.close()
    store.close()


def test_a_trail_replaced_with_a_new_key_is_caught_by_the_record_mac(tmp_path: Path) -> None:
    """Trail, head and key deleted together: a new trail starts, and the state's record
    (MACed under the old key) says the trail was replaced."""
    _gateway(tmp_path, range(3))
    for file in tmp_path.glob("audit.db*"):
        file.unlink()
    store = SqliteStore(tmp_path / "state.db")
    audit = AuditLog(tmp_path / "audit.db", clock=ManualClock())
    audit.attach(store.outbox())
    assert audit.rolled_back is not None and "replaced" in audit.rolled_back
    audit.close()
    store.close()


def test_an_export_proves_growth_and_fails_rollback_truncation_and_rewrite(
    tmp_path: Path,
) -> None:
    path, exported = tmp_path / "audit.db", tmp_path / "head.json"
    trail(path, 5)
    _copy_trail(tmp_path, tmp_path / "copy")
    log = AuditLog(path)
    append(log, 5)
    log.close()
    export_head(path, exported)
    log = AuditLog(path)
    append(log, 6)
    log.close()
    grown = verify(path, since=exported)
    assert grown.ok and "exported head at row 6: the chain extends it (MAC verified)" in (
        grown.lines()
    )
    _restore_trail(tmp_path / "copy", tmp_path)  # rolled back to 5 rows
    back = verify(path, since=exported)
    assert (
        not back.ok and back.since is not None and "rolled back: row 6" in str(back.since.problem)
    )
    log = AuditLog(path)
    append(log, 99)  # row 6 again, another row
    log.close()
    rewritten = verify(path, since=exported)
    assert not rewritten.ok
    assert rewritten.since is not None
    assert (
        rewritten.since.problem
        == "rolled back or rewritten: row 6 holds another hash than recorded"
    )
    said = CliRunner().invoke(main, ["audit", "verify", str(path), "--since", str(exported)])
    assert said.exit_code == 1 and f"{ROLLED_BACK}: against the exported head" in said.output


def test_a_forged_export_is_refused(tmp_path: Path) -> None:
    path, exported = tmp_path / "audit.db", tmp_path / "head.json"
    trail(path, 3)
    export_head(path, exported)
    exported.write_bytes(exported.read_bytes().replace(b'"rows": 3', b'"rows": 2'))
    with pytest.raises(AuditFileError, match="head MAC does not verify"):
        verify(path, since=exported)
    said = CliRunner().invoke(main, ["audit", "verify", str(path), "--since", str(exported)])
    assert said.exit_code == 2 and "head MAC does not verify" in said.output


def test_an_exported_row_removed_by_retention_is_not_comparable(tmp_path: Path) -> None:
    path, exported = tmp_path / "audit.db", tmp_path / "head.json"
    trail(path, 1)
    export_head(path, exported)
    budget = 3 * SMALL_SEGMENT + 8192
    segmented(path, 300, Retention(segment_bytes=SMALL_SEGMENT, max_bytes=budget)).close()
    report = verify(path, since=exported)
    assert report.ok and report.since is not None and report.since.cut is not None
    assert "row 1 was removed by retention" in report.since.cut
    assert "not that the rows removed were the ones recorded" in report.since.cut


def test_a_trail_that_does_not_verify_is_not_exported(tmp_path: Path) -> None:
    path = tmp_path / "audit.db"
    trail(path, 3)
    sql(path, "UPDATE audit SET sender = 'mallory' WHERE seq = 2")
    said = CliRunner().invoke(main, ["audit", "head", str(path), "--export", str(tmp_path / "h")])
    assert said.exit_code == 2 and "not exported" in said.output
    assert not (tmp_path / "h").exists()


def test_verify_state_on_a_file_that_is_not_a_database_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "audit.db"
    trail(path, 1)
    (tmp_path / "state.db").write_text("not a database")
    said = CliRunner().invoke(main, ["audit", "verify", str(path), "--state",
                                     str(tmp_path / "state.db")])  # fmt: skip
    assert said.exit_code == 2 and "not a readable SQLite state database" in said.output


def test_a_state_database_put_back_behind_the_trail_is_rolled_back_too(tmp_path: Path) -> None:
    """The reverse: the trail intact, the state database restored from an older copy (its
    outbox never reached the trail's mark)."""
    _gateway(tmp_path, range(3))
    old = tmp_path / "old"
    old.mkdir()
    for file in tmp_path.glob("state.db*"):
        shutil.copy2(file, old / file.name)
    _gateway(tmp_path, range(3, 6))
    for file in tmp_path.glob("state.db*"):
        file.unlink()
    for file in old.iterdir():
        shutil.copy2(file, tmp_path / file.name)
    store = SqliteStore(tmp_path / "state.db")
    audit = AuditLog(tmp_path / "audit.db", clock=ManualClock())
    audit.attach(store.outbox())
    assert audit.rolled_back is not None and "is behind the trail" in audit.rolled_back
    _put(audit, 6)  # rows put from now on are moved, never skipped (a new epoch)
    assert [r.msg_id for r in audit.tail(2)] == [None, "m6"]
    audit.close()
    store.close()
