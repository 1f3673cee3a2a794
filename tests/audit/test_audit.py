"""The audit trail: its hash chain, its head anchored outside the database (truncation, rewrite,
missing checkpoint), foreign files, and what the receive path writes to it."""

from __future__ import annotations

import json
import os
import sqlite3
from pathlib import Path

import pytest
from click.testing import CliRunner

from antireplay.audit import GENESIS, AuditLog, AuditRow, reanchor, verify
from antireplay.audit.chain import _digest
from antireplay.cli import main
from antireplay.core.clock import ManualClock
from antireplay.core.errors import AuditFileError, StateUnavailableError
from antireplay.rcan.receive import Receiver
from antireplay.wiring import build_receiver, embedded_default
from harness.audit import sql, trail
from harness.envelopes import MARKER, NOW, message, signed


@pytest.fixture
def db(tmp_path: Path) -> Path:
    path = tmp_path / "audit.db"
    trail(path, 5)
    return path


def test_intact_trail_is_proven_to_its_head(db: Path) -> None:
    report = verify(db)
    assert report.ok and report.records == 5 and report.checkpoint_rows == 5
    assert report.lines() == [
        "chain intact to row 5 (5 records)",
        "head checkpoint matches row 5 (MAC verified)",
    ]
    assert db.with_name("audit.db.key").stat().st_mode & 0o777 == 0o600


def test_deleting_the_newest_rows_is_detected(db: Path) -> None:
    sql(db, "DELETE FROM audit WHERE seq > 3")
    report = verify(db)
    assert report.chain_ok and report.records == 3  # the chain alone cannot see it
    assert not report.ok and "truncated" in report.head
    with pytest.raises(AuditFileError, match="truncated") as err:
        AuditLog(db)  # the gateway / proxy refuses to start on it
    assert str(db) in str(err.value) and f"antireplay audit reanchor {db}" in str(err.value)


def test_wholesale_rewrite_without_the_key_is_detected(db: Path) -> None:
    """Whoever can write the database recomputes a perfect chain; the head MAC still differs."""
    sql(db, "DELETE FROM audit")
    prev, conn = GENESIS, sqlite3.connect(db)
    for seq in range(1, 6):
        row = dict(seq=seq, at=1.0, outcome="accepted", code=None, warning=None, msg_type=1,
                   sender="someone-else", sender_verified=1, msg_id=f"x{seq}")  # fmt: skip
        digest = _digest(prev, row)
        conn.execute(
            "INSERT INTO audit VALUES (?,?,?,?,?,?,?,?,?,?,?)", (*row.values(), prev, digest)
        )
        prev = digest
    conn.commit()
    conn.close()
    report = verify(db)
    assert report.chain_ok and report.records == 5
    assert not report.ok and "rewritten" in report.head
    with pytest.raises(AuditFileError, match="rewritten"):
        AuditLog(db)
    # nor can the attacker write a new checkpoint without the key
    head = db.with_name("audit.db.head")
    head.write_text(head.read_text().replace('"rows": 5', '"rows": 4'))
    report = verify(db)
    assert not report.ok and "head MAC does not verify" in report.head


def test_missing_checkpoint_is_reported_and_refused_until_reanchored(db: Path) -> None:
    db.with_name("audit.db.head").unlink()
    report = verify(db)
    assert not report.ok and report.head == "missing"
    assert (
        "head checkpoint missing: cannot prove the newest rows were not deleted" in report.lines()
    )
    with pytest.raises(AuditFileError, match="missing") as err:
        AuditLog(db)
    assert "audit.db.head" in str(err.value)
    reanchor(db)  # the operator checked the trail and accepts its current head
    assert verify(db).ok
    trail(db, 1)
    assert verify(db).records == 6


def test_rows_after_the_last_checkpoint_are_counted_not_proven(db: Path) -> None:
    """A crash between the commit and the checkpoint leaves rows the MAC does not cover."""
    head = db.with_name("audit.db.head")
    saved = head.read_bytes()
    trail(db, 2)
    head.write_bytes(saved)  # as if the process died before writing the last checkpoints
    report = verify(db)
    assert report.ok and report.after_checkpoint == 2
    assert any("rows after the last checkpoint: 2" in line for line in report.lines())
    AuditLog(db).close()  # reopening adopts them into a new checkpoint
    assert verify(db).after_checkpoint == 0


def test_missing_or_damaged_key_is_refused(db: Path) -> None:
    key = db.with_name("audit.db.key")
    key.chmod(0o644)
    with pytest.raises(AuditFileError, match="chmod 600"):
        AuditLog(db)
    key.write_text("not a key")
    key.chmod(0o600)
    with pytest.raises(AuditFileError, match="not an audit head key") as err:
        AuditLog(db)
    assert str(key) in str(err.value)
    key.unlink()
    with pytest.raises(AuditFileError, match="missing while the head checkpoint exists"):
        AuditLog(db)
    assert verify(db).head == "no-key" and not verify(db).ok


def test_trail_without_key_and_checkpoint_waits_for_an_operator(db: Path) -> None:
    """Made before anchoring, or both files deleted to hide a truncation: never silently."""
    db.with_name("audit.db.head").unlink()
    db.with_name("audit.db.key").unlink()
    sql(db, "DELETE FROM audit WHERE seq > 3")
    with pytest.raises(AuditFileError, match="has 3 rows but no head checkpoint or key"):
        AuditLog(db)
    assert not db.with_name("audit.db.key").exists()
    result = CliRunner().invoke(main, ["audit", "reanchor", str(db)])
    assert result.exit_code == 0 and "re-anchored" in result.output
    assert verify(db).ok
    AuditLog(db).close()


@pytest.mark.parametrize(
    "content", [b"garbage " * 100, b"SQLite format 3\x00" + b"\xff" * 200, b"\x00" * 4096]
)
def test_garbage_audit_file_is_refused_naming_the_file(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "audit.db"
    path.write_bytes(content)
    for opener in (AuditLog, verify):
        with pytest.raises(AuditFileError) as err:
            opener(path)
        assert str(path) in str(err.value) and "Recover with" in str(err.value)
    assert path.read_bytes() == content


def test_foreign_database_is_refused_and_left_untouched(tmp_path: Path) -> None:
    path = tmp_path / "users.db"
    sql(path, "CREATE TABLE users (name TEXT)")
    with pytest.raises(AuditFileError, match="not an audit trail"):
        AuditLog(path)
    with pytest.raises(AuditFileError, match="not an audit trail"):
        verify(path)
    conn = sqlite3.connect(path)
    tables = [r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")]
    conn.close()
    assert tables == ["users"]  # no audit table created in somebody else's file


# --- the CLI ------------------------------------------------------------------------------------


def test_cli_verify_says_what_it_proves(db: Path) -> None:
    result = CliRunner().invoke(main, ["audit", "verify", str(db)])
    assert result.exit_code == 0, result.output
    assert "chain intact to row 5" in result.output
    assert "head checkpoint matches row 5" in result.output


def test_cli_verify_exits_non_zero_on_truncation_and_rewrite(db: Path) -> None:
    sql(db, "DELETE FROM audit WHERE seq = 5")
    result = CliRunner().invoke(main, ["audit", "verify", str(db)])
    assert result.exit_code == 1
    assert "chain intact to row 4" in result.output and "truncated" in result.output
    sql(db, "UPDATE audit SET sender = 'x' WHERE seq = 2")
    result = CliRunner().invoke(main, ["audit", "verify", str(db)])
    assert result.exit_code == 1 and "chain broken at row 2" in result.output


def test_cli_verify_on_a_non_database_is_an_error_not_a_traceback(tmp_path: Path) -> None:
    path = tmp_path / "notes.txt"
    path.write_text("hello\n" * 50)
    result = CliRunner().invoke(main, ["audit", "verify", str(path)])
    assert result.exit_code == 2
    assert result.exception is None or isinstance(result.exception, SystemExit)
    said = " ".join(result.output.split())  # the console may wrap; the words must be there
    assert "not an SQLite database" in said and str(path) in said and "Traceback" not in said


def test_cli_reanchor_refuses_a_broken_chain(db: Path) -> None:
    sql(db, "UPDATE audit SET sender = 'x' WHERE seq = 2")
    result = CliRunner().invoke(main, ["audit", "reanchor", str(db)])
    assert result.exit_code == 2 and "cannot re-anchor" in " ".join(result.output.split())


def test_cli_proxy_refuses_a_garbage_audit_file_naming_it(tmp_path: Path) -> None:
    key, audit = tmp_path / "key.hex", tmp_path / "audit.db"
    key.write_text("00" * 32)
    audit.write_bytes(b"\x13\x37" * 500)
    result = CliRunner().invoke(main, [
        "mavlink-proxy", "--listen", "udp:127.0.0.1:9", "--forward", "udp:127.0.0.1:9",
        "--key-file", str(key), "--store", f"sqlite:{tmp_path / 'mav.db'}",
        "--audit", str(audit),
    ])  # fmt: skip
    assert result.exit_code == 2
    said = " ".join(result.output.split())
    assert str(audit) in said and "not an SQLite database" in said and "Traceback" not in said
    assert not (tmp_path / "mav.db").exists()  # refused before anything was opened


def test_gateway_startup_on_a_garbage_audit_file_names_it(tmp_path: Path) -> None:
    config = embedded_default(tmp_path)
    Path(config.audit).write_bytes(b"PK\x03\x04" + bytes(500))  # a zip where the trail was
    with pytest.raises(AuditFileError) as err:
        build_receiver(config)
    assert f"audit file {config.audit}: not an SQLite database" in str(err.value)


def _append(log: AuditLog, mid: str) -> int:
    return log.append(AuditRow(
        at=1_800_000_100.0, outcome="accepted", code=None, warning=None, msg_type=1,
        sender="op", sender_verified=True, msg_id=mid,
    ))  # fmt: skip


def test_rows_deleted_under_a_running_writer_are_never_adopted(db: Path) -> None:
    log = AuditLog(db)
    _append(log, "m5")
    sql(db, "DELETE FROM audit WHERE seq > 3")  # someone truncates the live trail
    with pytest.raises(StateUnavailableError, match="truncated"):
        _append(log, "m6")  # the accept that needs this row is refused, not audited silently
    log.close()
    assert not verify(db).ok  # and the evidence stays: the checkpoint still says 6 rows


def test_a_second_writer_extending_the_chain_is_fine(db: Path) -> None:
    one, two = AuditLog(db), AuditLog(db)
    _append(one, "a")
    _append(two, "b")
    _append(one, "c")
    one.close()
    two.close()
    assert verify(db).ok and verify(db).records == 8


def _head_syncs(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Record which files ``os.fdatasync`` makes durable (the head's cadence)."""
    synced: list[str] = []
    real = os.fdatasync

    def counting(fd: int) -> None:
        synced.append(Path(os.readlink(f"/proc/self/fd/{fd}")).name)
        real(fd)

    monkeypatch.setattr(os, "fdatasync", counting)
    return synced


def test_head_is_rewritten_every_batch_but_fsynced_on_its_cadence(
    db: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    clock = ManualClock()
    synced = _head_syncs(monkeypatch)
    log = AuditLog(db, head_sync_s=1.0, clock=clock)
    for i in range(4):
        _append(log, f"n{i}")
    assert synced == []  # four batches, no head fsync yet
    # ...but each batch rewrote the head: a kill -9 now leaves it covering every answered row
    report = verify(db)
    assert report.ok and report.checkpoint_rows == 9 and report.after_checkpoint == 0
    clock.advance(1.0)
    _append(log, "n4")
    assert synced == ["audit.db.head"]
    _append(log, "n5")
    log.close()  # the last, unsynced head is made durable on close
    assert synced == ["audit.db.head", "audit.db.head"]
    assert verify(db).ok and verify(db).checkpoint_rows == 11


def test_rollback_below_an_unsynced_head_is_still_detected(db: Path) -> None:
    """The cadence only delays the head's fsync: the head a crashed writer left still
    refuses a database rolled back below it."""
    log = AuditLog(db, head_sync_s=3600.0, clock=ManualClock())
    for i in range(3):
        _append(log, f"n{i}")
    # the writer dies here (no close, as under kill -9); the database goes back two rows
    sql(db, "DELETE FROM audit WHERE seq > 6")
    report = verify(db)
    assert report.chain_ok and not report.ok and "truncated" in report.head
    with pytest.raises(AuditFileError, match="truncated"):
        AuditLog(db)
    log.close()


def test_a_power_cut_brings_back_an_older_head_that_only_under_claims(db: Path) -> None:
    """An un-fsynced head lost in a power cut leaves the last synced one: rows after it are
    reported as not covered, never as proven, and a truncation below it is still refused."""
    head = db.with_name("audit.db.head")
    synced = head.read_bytes()
    log = AuditLog(db, head_sync_s=3600.0, clock=ManualClock())
    for i in range(3):
        _append(log, f"n{i}")
    log.close()
    head.write_bytes(synced)  # what the disk held after the cut: the head fsynced at 5 rows
    report = verify(db)
    assert report.ok and report.checkpoint_rows == 5 and report.after_checkpoint == 3
    sql(db, "DELETE FROM audit WHERE seq > 4")
    assert "truncated" in verify(db).head


def test_cli_tail_never_writes_the_trail(db: Path) -> None:
    """tail must not adopt uncovered rows (someone's forged appends) into a new checkpoint."""
    head = db.with_name("audit.db.head")
    saved = head.read_bytes()
    trail(db, 1)
    head.write_bytes(saved)  # one row the checkpoint does not cover
    result = CliRunner().invoke(main, ["audit", "tail", str(db)])
    assert result.exit_code == 0, result.output
    assert head.read_bytes() == saved
    assert verify(db).after_checkpoint == 1


# --- what the receive path writes ---------------------------------------------------------------


def test_audit_chain_verifies_and_tamper_is_found(tmp_path: Path, receiver: Receiver) -> None:
    raw = signed()
    receiver.receive(raw)
    receiver.receive(raw)
    receiver.receive(signed(timestamp=NOW - 100))
    receiver.receive(signed())
    path = tmp_path / "audit.db"
    report = verify(path)
    assert report.ok and report.records == 4
    db = sqlite3.connect(path)
    db.execute("UPDATE audit SET code = 'OK' WHERE seq = 2")
    db.commit()
    db.close()
    report = verify(path)
    assert (report.ok, report.broken_at) == (False, 2)


def test_audit_deleted_record_is_found(tmp_path: Path, receiver: Receiver) -> None:
    for _ in range(3):
        receiver.receive(signed())
    db = sqlite3.connect(tmp_path / "audit.db")
    db.execute("DELETE FROM audit WHERE seq = 2")
    db.commit()
    db.close()
    assert verify(tmp_path / "audit.db").broken_at == 2


def test_no_payload_ever_reaches_the_audit_database(tmp_path: Path, receiver: Receiver) -> None:
    hostile_id = f"id\n2026-01-01 ACCEPTED admin {MARKER}"
    raw = signed(msg_id=hostile_id[:100])
    receiver.receive(raw)
    receiver.receive(raw)
    forged = {**message(), "sig": {"alg": "x", "kid": "k", "value": "y"}}
    receiver.receive(json.dumps(forged).encode())
    receiver.receive(signed(timestamp=NOW - 99, sender="claimed-bob"))
    assert receiver.audit is not None
    receiver.audit.close()
    blob = b"".join(p.read_bytes() for p in tmp_path.iterdir() if p.name.startswith("audit.db"))
    assert MARKER.encode() not in blob
    assert b"\n2026-01-01" not in blob
    records = AuditLog(tmp_path / "audit.db").tail()
    assert all("\n" not in (r.msg_id or "") for r in records)
    assert [r.sender_verified for r in records if r.sender == "claimed-bob"] == [False]
