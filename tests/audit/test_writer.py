"""The audit writer when its trail is deleted: refused at start, refused while running."""

from __future__ import annotations

from pathlib import Path

import pytest

from antireplay.audit import AuditLog
from antireplay.core.errors import AuditFileError, StateUnavailableError
from tests.harness.audit import trail


@pytest.mark.parametrize("key_too", [False, True], ids=["db", "db-and-key"])
def test_a_refused_start_on_a_deleted_trail_creates_nothing(tmp_path: Path, key_too: bool) -> None:
    """``rm audit.db*`` under a running gateway (which rewrites its head afterwards): the next
    start refuses, says the trail was deleted and how many records the head says it held, and
    leaves no new empty trail behind for the start after that to adopt."""
    path = tmp_path / "audit.db"
    trail(path, 3)
    doomed = [path, *tmp_path.glob("audit.db-*")]
    if key_too:
        doomed.append(tmp_path / "audit.db.key")
    for file in doomed:
        file.unlink()
    with pytest.raises(AuditFileError) as err:
        AuditLog(path)
    assert "deleted" in err.value.problem
    assert "held 3 records" in err.value.problem
    assert not path.exists()


def test_a_running_writer_refuses_to_append_to_a_deleted_trail(tmp_path: Path) -> None:
    """Deleted under a running writer, a trail would swallow every later record with the
    unlinked file: the append fails (503 for the command) instead of being lost."""
    trail(tmp_path / "audit.db", 1)
    log = AuditLog(tmp_path / "audit.db")
    try:
        for file in tmp_path.glob("audit.db*"):
            file.unlink()
        with pytest.raises(StateUnavailableError, match="deleted or replaced"):
            log.append(
                at=1_800_000_100.0, outcome="accepted", code=None, warning=None, msg_type=1,
                sender="operator", sender_verified=True, msg_id="lost",
            )  # fmt: skip
    finally:
        log.close()
