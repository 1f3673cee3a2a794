"""The shared revocation list on each backend: revoke and unrevoke move the counter the
watchers poll, the set is what every process reads, and a store that is down is
``STATE_UNAVAILABLE``, never a traceback."""

from __future__ import annotations

import stat
from collections.abc import Iterator
from pathlib import Path

import pytest

from antireplay.core.errors import StateUnavailableError
from antireplay.state import StoreSpec
from antireplay.state.revocations import (
    RELOADS,
    REVOCATIONS,
    MemoryRevocations,
    RevocationList,
    SqliteRevocations,
    open_revocations,
    sqlite_path,
)
from harness.redis_server import RedisServer


@pytest.fixture(params=["memory", "sqlite", "redis"])
def two(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[RevocationList, ...]]:
    """Two handles on one list, as two processes on one state hold them."""
    if request.param == "memory":
        shared = MemoryRevocations()
        yield shared, shared
        return
    server = None
    if request.param == "redis":
        server = RedisServer(tmp_path)
        server.start()
        spec = StoreSpec.parse(server.url)
    else:
        spec = StoreSpec.parse(f"sqlite:{tmp_path / 'state.db'}")
    a, b = open_revocations(spec), open_revocations(spec)
    try:
        yield a, b
    finally:
        a.close()
        b.close()
        if server is not None:
            server.stop()


def test_a_revocation_is_seen_by_another_handle_and_moves_the_counter(
    two: tuple[RevocationList, RevocationList],
) -> None:
    a, b = two
    before = b.counters()
    assert a.revoke("op-1") is True
    assert a.revoke("op-1") is False  # already revoked: said, still counted
    assert b.revoked() == {"op-1"}
    assert b.counters()[REVOCATIONS] == before[REVOCATIONS] + 2
    assert b.unrevoke("op-1") is True and a.revoked() == frozenset()
    a.request_reload()
    assert b.counters()[RELOADS] == before[RELOADS] + 1


def test_the_sqlite_list_lives_beside_the_state_not_under_its_glob(tmp_path: Path) -> None:
    path = sqlite_path(tmp_path / "state.db")
    assert path == tmp_path / "state.revocations.db"
    assert not path.name.startswith("state.db")  # `rm state.db*` does not un-revoke


def test_an_unreachable_redis_is_state_unavailable(tmp_path: Path) -> None:
    server = RedisServer(tmp_path)
    server.start()
    revocations = open_revocations(StoreSpec.parse(server.url))
    server.stop()
    for call in (revocations.counters, revocations.revoked, lambda: revocations.revoke("k")):
        with pytest.raises(StateUnavailableError):
            call()


def test_the_sqlite_list_is_created_0600(tmp_path: Path) -> None:
    revocations = SqliteRevocations(tmp_path / "state.revocations.db")
    revocations.revoke("op-1")
    revocations.close()
    for made in tmp_path.glob("state.revocations.db*"):
        assert stat.S_IMODE(made.stat().st_mode) == 0o600, made
