"""Stateful property test: ReplayCache over every real backend against a reference model.

One rule set drives the memory store, a SQLite file and a real redis-server through
fresh messages, exact replays, time passing, wall-clock steps both ways, restarts and
data loss (a deleted or rolled-back SQLite file; a flushed or restarted Redis).  The
model is §8.3 with unbounded memory; the implementation must agree with it exactly on
staleness and the future, must never accept an exact copy of an accepted message twice
(a fresh ESTOP is accepted again, with ``REPLAY_DETECTED``), and may refuse beyond the
model only for a reason it can show: the restart fence, the watermark, saturation.

Loss events run only while the wall clock is at its highest reading so far (and a loss
Redis has not noticed yet blocks steps back): a store that forgot state while its clock
stood behind what it had already accepted cannot fence what it never knew it accepted.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule

from antireplay import ManualClock, MessageType, ReplayAttackError, ReplayCache
from antireplay.core.errors import (
    MessageFromFutureError,
    MessageStaleError,
    ReplayDetectedError,
    StateUnavailableError,
)
from antireplay.state import ReplayStore
from antireplay.state.memory import MemoryStore
from antireplay.state.redis import RedisStore
from antireplay.state.sqlite import SqliteStore
from harness.redis_server import RedisServer
from harness.stores import sqlite_store

WINDOW, SAFETY_WINDOW, SKEW, MEMORY_MAX = 30.0, 10.0, 5.0, 6
#: Far enough ahead of the real clock that Redis's server time never sets a fence.
NOW = 2_000_000_000.0
#: Stores are created this long before NOW: their start-up fence is long past.
STARTED = NOW - 400
#: The wall clock never steps back further than this below its highest reading.
MAX_BACK = 60.0

Kind = tuple[int, str | None]
Exact = tuple[str, float, int, str | None]
IDS = st.sampled_from([f"id{i}" for i in range(8)])
OFFSETS = st.one_of(st.integers(-45, 10).map(float), st.floats(-45, 10, allow_nan=False))
KINDS = st.sampled_from(
    [
        (MessageType.COMMAND, None),
        (MessageType.SAFETY, "ESTOP"),
        (MessageType.SAFETY, "RESUME"),
    ]
)
ALLOWED_EXTRA = {"restart_fence", "watermark", "saturated"}

_server: RedisServer | None = None


@pytest.fixture(scope="module", autouse=True)
def redis_for_the_module(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """One real redis-server (with RDB snapshots) for every Redis example of this module."""
    global _server  # noqa: PLW0603 - state machines cannot take fixtures
    _server = RedisServer(tmp_path_factory.mktemp("redis-model"), snapshots=True)
    _server.start()
    try:
        yield
    finally:
        _server.stop()
        _server = None


def server() -> RedisServer:
    if _server is None:
        pytest.fail("the module's redis-server is not running")
    return _server


@dataclass
class Model:
    """Unbounded §8.3: every accepted msg_id and every exact message, until expiry."""

    seen: dict[str, float] = field(default_factory=dict)
    exact: dict[Exact, float] = field(default_factory=dict)
    #: msg_ids a commit recorded although the window then refused the message (fence, watermark)
    burned: dict[str, float] = field(default_factory=dict)

    def decide(self, mid: str, ts: float, kind: Kind, now: float) -> str:
        msg_type, event = kind
        window = SAFETY_WINDOW if msg_type == MessageType.SAFETY else WINDOW
        if now - ts > window:
            return "stale"
        if ts > now + SKEW:
            return "future"
        live = self.seen.get(mid, -1.0) >= now
        if msg_type == MessageType.SAFETY and event == "ESTOP":
            return "accept-warn" if live else "accept"
        return "replay" if live else "accept"

    def record(self, mid: str, ts: float, kind: Kind) -> None:
        window = SAFETY_WINDOW if kind[0] == MessageType.SAFETY else WINDOW
        self.seen[mid] = max(self.seen.get(mid, -1.0), ts + window)
        self.exact[(mid, ts, kind[0], kind[1])] = ts + window


class StoreVsModel(RuleBasedStateMachine):
    """The shared rules; subclasses open, restart and lose their backend's state."""

    def __init__(self) -> None:
        super().__init__()
        self.clock = ManualClock(wall=STARTED)
        self.store = self.open()
        self.cache = ReplayCache(WINDOW, 10_000, SKEW, self.clock, store=self.store)
        self.clock.advance(NOW - STARTED)
        self.high = self.clock.wall()
        self.model = Model()
        self.stepped_back = False
        self.losses = 0  # restarts and data-loss events so far (msg_id entries may be gone)
        self.pending_loss = False  # Redis lost state and has not been told yet

    # --- backend hooks -------------------------------------------------------------------

    def open(self) -> ReplayStore:
        raise NotImplementedError

    def reopen(self, store: ReplayStore) -> None:
        self.store = store
        self.cache = ReplayCache(WINDOW, 10_000, SKEW, self.clock, store=store)

    def teardown(self) -> None:
        self.store.close()

    # --- messages ------------------------------------------------------------------------

    @rule(mid=IDS, offset=OFFSETS, kind=KINDS)
    def send(self, mid: str, offset: float, kind: Kind) -> None:
        self.deliver(mid, self.clock.wall() + offset, kind)

    @rule(data=st.data())
    def replay_exact(self, data: st.DataObject) -> None:
        """Resend an exact copy (msg_id, timestamp, type, event) of an accepted message."""
        if not self.model.exact:
            return
        mid, ts, msg_type, event = data.draw(st.sampled_from(sorted(self.model.exact, key=repr)))
        self.deliver(mid, ts, (msg_type, event))

    def deliver(self, mid: str, ts: float, kind: Kind) -> None:
        now = self.clock.wall()
        expected = self.model.decide(mid, ts, kind, now)
        exact = (mid, ts, kind[0], kind[1]) in self.model.exact
        noticed = self.store.status().get("data_loss_events", 0)
        try:
            verdict = self.cache.commit(mid, ts, kind[0], kind[1])
        except StateUnavailableError as exc:
            raise AssertionError(f"the store was unreachable outside a restart: {exc}") from None
        except ReplayAttackError as exc:
            # Told only if the commit reached the store: a refusal by the fence this process
            # already knows (or by staleness) never does.
            self.pending_loss &= self.store.status().get("data_loss_events", 0) == noticed
            self.refused(expected, exc, (mid, ts, kind[0], kind[1]), now)
            return
        self.pending_loss = False
        assert expected not in {"stale", "future"}, (expected, "accepted", verdict)
        estop = kind == (MessageType.SAFETY, "ESTOP")
        assert not (exact and not estop), f"an exact copy was accepted twice: {mid, ts, kind}"
        if exact:
            assert verdict.warning == "REPLAY_DETECTED", verdict
        if expected == "replay":
            assert self.degraded, "a live msg_id was accepted again with nothing forgotten"
        if expected == "accept-warn" and not self.degraded:
            assert verdict.warning == "REPLAY_DETECTED", verdict
        self.model.record(mid, ts, kind)

    def refused(self, expected: str, exc: ReplayAttackError, message: Exact, now: float) -> None:
        """The model's refusals match exactly; anything more must show its reason."""
        mid, ts, msg_type, event = message
        if expected == "stale":
            assert type(exc) is MessageStaleError and exc.detail is None, exc
            return
        if expected == "future":
            assert type(exc) is MessageFromFutureError, exc
            return
        window = SAFETY_WINDOW if msg_type == MessageType.SAFETY else WINDOW
        if type(exc) is ReplayDetectedError:
            # The store records before the window judges, so a message refused by the fence
            # or the watermark still holds its msg_id until its expiry (fail closed).
            assert expected == "replay" or self.model.burned.get(mid, -1.0) >= now, (exc, mid)
            return
        assert (msg_type, event) != (MessageType.SAFETY, "ESTOP"), f"fresh ESTOP refused: {exc!r}"
        assert type(exc) is MessageStaleError and exc.detail in ALLOWED_EXTRA, (expected, exc)
        status = self.store.status()
        if exc.detail != "saturated":
            self.model.burned[mid] = max(self.model.burned.get(mid, -1.0), ts + window)
        if exc.detail == "restart_fence":
            assert self.losses > 0, "a fence refusal with no restart or loss since the start"
            assert ts <= status["fence"] + SKEW, (ts, status)
            assert status["fence"] <= self.high + 1e-5, (status, self.high)
        elif exc.detail == "watermark":
            assert self.stepped_back or status["evictions"] > 0, (exc, status)
            assert ts + window <= status["watermark"], (ts, status)
        else:
            assert isinstance(self.store, MemoryStore) and len(self.store) >= MEMORY_MAX

    @property
    def degraded(self) -> bool:
        """Whether the store may have forgotten a live msg_id (and must fence exact copies)."""
        return self.stepped_back or self.losses > 0 or self.store.status()["evictions"] > 0

    # --- time ----------------------------------------------------------------------------

    @rule(seconds=st.floats(0, 40, allow_nan=False))
    def wait(self, seconds: float) -> None:
        self.clock.advance(seconds)
        self.high = max(self.high, self.clock.wall())

    @rule(seconds=st.floats(0.1, 30, allow_nan=False))
    def ntp_step_forward(self, seconds: float) -> None:
        self.clock.step_wall(seconds)
        self.high = max(self.high, self.clock.wall())

    @precondition(lambda self: not self.pending_loss)
    @rule(seconds=st.floats(0.1, 30, allow_nan=False))
    def ntp_step_back(self, seconds: float) -> None:
        self.clock.step_wall(-min(seconds, self.clock.wall() - (self.high - MAX_BACK)))
        self.stepped_back = True

    def at_high(self) -> bool:
        return self.clock.wall() >= self.high

    @invariant()
    def fence_never_ahead_of_the_clock(self) -> None:
        assert self.store.status()["fence"] <= self.high + 1e-5  # Redis adds 1 µs


class MemoryVsModel(StoreVsModel):
    def open(self) -> ReplayStore:
        return MemoryStore(max_entries=MEMORY_MAX, clock=self.clock)

    @precondition(StoreVsModel.at_high)
    @rule()
    def restart(self) -> None:
        """A new process: everything is forgotten, behind a fence at its start."""
        self.reopen(MemoryStore(max_entries=MEMORY_MAX, clock=self.clock))
        self.losses += 1

    @invariant()
    def bounded(self) -> None:
        assert int(self.store.status()["entries"]) <= MEMORY_MAX


class SqliteVsModel(StoreVsModel):
    def open(self) -> ReplayStore:
        # tmpfs when there is one: this test is about the logic, and fsync on a shared disk
        # would make it slow (durability under kill -9: tests/state/test_state.py).
        shm = Path("/dev/shm")
        where = shm if shm.is_dir() else None
        self.dir = Path(tempfile.mkdtemp(prefix="antireplay-model-", dir=where))
        self.path = self.dir / "state.db"
        self.snapshot: Path | None = None
        return sqlite_store(self.path, clock=self.clock)

    def teardown(self) -> None:
        super().teardown()
        shutil.rmtree(self.dir, ignore_errors=True)

    def replace_file(self, source: Path | None) -> None:
        """Close, put ``source`` (or nothing) where the database was, keep the witness, open."""
        self.store.close()
        for suffix in ("", "-wal", "-shm"):
            self.path.with_name(self.path.name + suffix).unlink(missing_ok=True)
        if source is not None:
            shutil.copyfile(source, self.path)
        self.reopen(SqliteStore(self.path, clock=self.clock))

    @rule()
    def restart(self) -> None:
        """A clean restart keeps everything and raises no fence."""
        fence = self.store.status()["fence"]
        self.store.close()
        self.reopen(SqliteStore(self.path, clock=self.clock))
        assert self.store.status()["fence"] == fence

    @rule()
    def take_snapshot(self) -> None:
        """A backup copy of the database (after a clean close, so it is self-contained)."""
        self.store.close()
        self.snapshot = self.dir / "backup.db"
        shutil.copyfile(self.path, self.snapshot)
        self.reopen(SqliteStore(self.path, clock=self.clock))

    @precondition(StoreVsModel.at_high)
    @rule()
    def delete_database(self) -> None:
        self.replace_file(None)
        self.noticed_loss()

    @precondition(lambda self: self.snapshot is not None and self.at_high())
    @rule()
    def restore_backup(self) -> None:
        self.replace_file(self.snapshot)
        self.noticed_loss()

    def noticed_loss(self) -> None:
        assert self.store.status()["fence"] == self.clock.wall(), self.store.status()
        self.losses += 1


class RedisVsModel(StoreVsModel):
    def open(self) -> ReplayStore:
        self.prefix = f"model-{uuid.uuid4().hex}:"
        made = self.client()
        made.verify()  # a new deployment: first contact raises the fence (at STARTED)
        return made

    def client(self) -> RedisStore:
        return RedisStore(server().url, prefix=self.prefix, clock=self.clock, skew_s=SKEW)

    @rule()
    def restart(self) -> None:
        """A new gateway process on the same Redis: nothing lost, no new fence."""
        fence = self.store.status()["fence"]
        self.store.close()
        fresh = self.client()
        self.reopen(fresh)
        if not self.pending_loss:
            assert fresh.verify().fence == fence

    @precondition(StoreVsModel.at_high)
    @rule()
    def flushdb(self) -> None:
        """FLUSHDB: noticed lazily, by the next commit (which must raise the fence)."""
        server().client().flushdb()
        self.losses += 1
        self.pending_loss = True

    @rule()
    def snapshot(self) -> None:
        server().save()

    @precondition(StoreVsModel.at_high)
    @rule()
    def restart_server(self) -> None:
        """kill -9 and start: from the last snapshot (maybe older than our writes) or empty."""
        redis_server = server()
        redis_server.kill()
        redis_server.start()
        self.losses += 1
        store = self.store
        assert isinstance(store, RedisStore)
        with contextlib.suppress(StateUnavailableError):
            store.verify()  # a pooled connection that the restart cut answers 503 once
        seen = store.verify()
        assert seen.fence >= self.clock.wall(), seen
        self.pending_loss = False


def configure(machine: type[StoreVsModel], examples: int) -> type[object]:
    machine.TestCase.settings = settings(
        max_examples=examples,
        stateful_step_count=35,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow],
    )
    return machine.TestCase


TestMemoryVsModel = configure(MemoryVsModel, 80)
TestSqliteVsModel = configure(SqliteVsModel, 60)
TestRedisVsModel = configure(RedisVsModel, 40)
