"""SqliteStore: a stored value that does not decode (a hand-edited row) refuses the start,
or answers 503 while serving, naming the file and the recovery, never a bare error."""

from __future__ import annotations

import sqlite3
import time
from functools import partial
from pathlib import Path

import pytest

from antireplay import ManualClock, MessageType, ReplayCache
from antireplay.core.errors import StateFileError, StateUnavailableError
from antireplay.state.sqlite import SAFETY_WAIT_S, STALLED_WAIT_S, SqliteStore, check_readable
from harness.stores import sqlite_store

NOW = 2_000_000_000.0

#: Hand edits of a valid file, each leaving a value its column cannot mean.
EDITS = {
    "seen expiry as text": "UPDATE seen SET expires = 'abc'",
    "seen expiry as a blob": "UPDATE seen SET expires = x'00ff'",
    "meta watermark": "UPDATE meta SET watermark = 'abc'",
    "meta fence": "UPDATE meta SET fence = 'abc'",
    "meta generation": "UPDATE meta SET generation = 'abc'",
    "meta data_loss_events": "UPDATE meta SET data_loss_events = 1.5",
    "meta deployment": "UPDATE meta SET deployment = 42",
}


def edit(db: Path, sql: str) -> None:
    conn = sqlite3.connect(db)
    try:
        conn.execute(sql)
        conn.commit()
    finally:
        conn.close()


def written(db: Path, clock: ManualClock) -> SqliteStore:
    """A store on ``db`` holding one live entry, ``cmd``."""
    store = sqlite_store(db, clock=clock)
    store.commit("cmd", NOW + 60, NOW)
    return store


@pytest.mark.parametrize("sql", EDITS.values(), ids=EDITS.keys())
def test_an_undecodable_value_refuses_the_open_and_the_check_naming_the_file(
    tmp_path: Path, sql: str
) -> None:
    db, clock = tmp_path / "state.db", ManualClock(wall=NOW)
    written(db, clock).close()
    edit(db, sql)
    before = db.read_bytes()
    with pytest.raises(StateFileError) as checked:
        check_readable(db)  # what ``config check`` runs: read-only
    assert db.read_bytes() == before
    with pytest.raises(StateFileError) as opened:
        sqlite_store(db, clock=clock)
    for refused in (checked.value, opened.value):
        assert refused.path == str(db)
        assert refused.recovery.startswith(f"mv {db} ")


@pytest.mark.parametrize(
    "sql", [EDITS["seen expiry as text"], EDITS["seen expiry as a blob"]], ids=["text", "blob"]
)
def test_an_undecodable_expiry_while_serving_is_503_naming_the_file(
    tmp_path: Path, sql: str
) -> None:
    db, clock = tmp_path / "state.db", ManualClock(wall=NOW)
    store = written(db, clock)
    edit(db, sql)
    for op in (partial(store.lookup, "cmd"), partial(store.commit, "cmd", NOW + 60, NOW)):
        with pytest.raises(StateUnavailableError) as err:
            op()
        assert str(db) in err.value.reason and "mv " in err.value.reason
    store.close()


@pytest.mark.parametrize("field", ["watermark", "fence", "generation"])
def test_an_undecodable_meta_while_serving_is_503_and_estop_still_passes(
    tmp_path: Path, field: str
) -> None:
    db, clock = tmp_path / "state.db", ManualClock(wall=NOW)
    store = written(db, clock)
    edit(db, f"UPDATE meta SET {field} = 'abc'")
    cache = ReplayCache(clock=clock, store=store)
    with pytest.raises(StateUnavailableError) as err:
        cache.commit("other", NOW)
    assert str(db) in err.value.reason
    with pytest.raises(StateUnavailableError):
        store.ready()
    with pytest.raises(StateFileError, match=str(db)):
        store.verify()
    assert cache.commit("estop", NOW, MessageType.SAFETY, "ESTOP").warning == "STATE_UNAVAILABLE"
    store.close()


def test_the_witness_claims_only_generations_made_durable(tmp_path: Path) -> None:
    """A deferred commit (no fsync of its own) moves the database, not the witness; the
    next durable commit's fsync covers it and the witness catches up: never ahead, so a
    power cut between the two cannot raise a false fence."""
    store = sqlite_store(tmp_path / "state.db")
    try:
        store.defer_commits()
        before = store.witness.read()
        assert isinstance(before, tuple)
        now = 1_800_000_000.0
        assert store.commit("deferred", now + 30.0, now).recorded
        assert store.witness.read() == before
        store.outbox().put({"outcome": "accepted"}, durable=True).result()
        after = store.witness.read()
        assert isinstance(after, tuple) and after[1] == before[1] + 2  # both generations
        assert store.commit("estop", now + 30.0, now, force=True).recorded  # never deferred
        latest = store.witness.read()
        assert isinstance(latest, tuple) and latest[1] == after[1] + 1
    finally:
        store.close()


def _busy_ms(store: SqliteStore) -> int:
    return int(store._db.execute("PRAGMA busy_timeout").fetchone()[0])


def test_another_process_holding_the_write_lock_costs_one_wait_and_an_estop_none(
    tmp_path: Path, clock: ManualClock
) -> None:
    """Another connection holds ``BEGIN IMMEDIATE`` (a second gateway stopped mid-batch):
    an ESTOP's commit gives up after ``SAFETY_WAIT_S`` (its record stays queued and lands
    once the lock frees); an ordinary commit waits the busy timeout once, and after that
    wait ran out every commit fails after ``STALLED_WAIT_S`` until a transaction begins."""
    store = sqlite_store(tmp_path / "state.db", timeout_s=30.0, clock=clock)
    now = clock.wall()
    holder = sqlite3.connect(tmp_path / "state.db", isolation_level=None)
    holder.execute("BEGIN IMMEDIATE")
    try:
        start = time.monotonic()
        with pytest.raises(StateUnavailableError, match="write lock not taken"):
            store.commit("estop-1", now + 60, now, force=True)
        assert time.monotonic() - start < 10 * SAFETY_WAIT_S  # not the 30 s busy timeout
    finally:
        holder.rollback()
    assert store.commit("a", now + 60, now).recorded  # queued behind the ESTOP's record
    assert store.lookup("estop-1").expiry == now + 60  # committed once the lock freed

    store._db.execute("PRAGMA busy_timeout=300")  # a short busy timeout to run out
    holder.execute("BEGIN IMMEDIATE")
    try:
        with pytest.raises(StateUnavailableError, match="locked"):
            store.commit("b", now + 60, now)  # one full wait
        assert _busy_ms(store) == int(STALLED_WAIT_S * 1000)
        with pytest.raises(StateUnavailableError, match="locked"):
            store.commit("c", now + 60, now)  # then at once
    finally:
        holder.rollback()
        holder.close()
    assert store.commit("d", now + 60, now).recorded
    assert _busy_ms(store) == 30_000  # the busy timeout is back
    store.close()
