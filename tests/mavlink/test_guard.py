"""MAVLink v2 guard: verify, bind, timestamp rules, and persistence behind a lease and a fence."""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay import ManualClock
from antireplay.core.errors import (
    CounterReplayedError,
    MessageFromFutureError,
    MessageStaleError,
    SignatureInvalidError,
    SignatureRequiredError,
    StateUnavailableError,
    WrongDirectionError,
    WrongTargetError,
)
from antireplay.mavlink import TS_LIMIT, UNITS_PER_S, MavlinkGuard, mav_time
from antireplay.mavlink.guard import FrameAdmission
from antireplay.mavlink.policy import lease_value
from antireplay.state.memory import MemoryStore
from antireplay.state.sqlite import SqliteStore
from harness.mavlink_frames import KEY, Sink, command_frame, encoder, unsigned_heartbeat
from harness.stores import sqlite_store


def test_signed_frame_accepted_once(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock, system_id=1)
    frame = command_frame(*encoder())
    assert guard.open(frame).signed
    with pytest.raises(CounterReplayedError):
        guard.open(frame)


def test_jamming_frame_changes_nothing(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock)
    mav, sink = encoder()
    guard.open(command_frame(mav, sink))
    jam = bytearray(command_frame(mav, sink))
    jam[-12:-6] = (TS_LIMIT - 1).to_bytes(6, "little")
    with pytest.raises(MessageFromFutureError):  # refused before the signature is computed
        guard.open(bytes(jam))
    jam[-12:-6] = (mav_time(clock) + UNITS_PER_S).to_bytes(6, "little")
    with pytest.raises(SignatureInvalidError):  # within the forward bound: the signature
        guard.open(bytes(jam))
    assert guard.open(command_frame(mav, sink)).signed  # later legitimate frames pass


def test_forged_new_streams_do_not_grow_the_table(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock)
    rng = random.Random(3)
    for _ in range(1_000):
        other = dialect.MAVLink(
            Sink(), srcSystem=rng.randint(1, 250), srcComponent=rng.randint(1, 250)
        )
        other.signing.secret_key = bytes(32)  # the attacker's key
        other.signing.sign_outgoing = True
        other.signing.link_id = rng.randint(0, 255)
        other.signing.timestamp = mav_time(clock)
        other.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        with pytest.raises(SignatureInvalidError):
            guard.open(other.file.frames[-1])
    assert len(guard) == 0


def test_new_stream_rule_uses_the_wall_clock(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock)
    old = command_frame(*encoder(ts=mav_time(clock) - 61 * UNITS_PER_S))
    with pytest.raises(MessageStaleError):
        guard.open(old)
    guard.open(command_frame(*encoder(link_id=2, ts=mav_time(clock) - 59 * UNITS_PER_S)))


def test_refusals_say_the_gap_in_seconds(clock: ManualClock) -> None:
    """What an operator asks when "signing does not work": how old, how far ahead."""
    guard = MavlinkGuard(KEY, clock=clock, new_stream_max_age_s=30, max_forward_s=5)
    with pytest.raises(MessageStaleError, match=r"new stream 45\.00 s behind .*limit 30\.00 s"):
        guard.open(command_frame(*encoder(ts=mav_time(clock) - 45 * UNITS_PER_S)))
    with pytest.raises(MessageFromFutureError, match=r"7\.50 s ahead .*limit 5\.00 s"):
        guard.open(command_frame(*encoder(ts=mav_time(clock) + 750_000)))
    mav, sink = encoder(ts=mav_time(clock))
    late = command_frame(mav, sink)
    mav.signing.timestamp += 2 * UNITS_PER_S
    guard.open(command_frame(mav, sink))
    with pytest.raises(CounterReplayedError, match=r"old timestamp: 2\.00 s behind the stream"):
        guard.open(late)


def test_forward_jump_bound(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock)
    with pytest.raises(MessageFromFutureError):
        guard.open(command_frame(*encoder(ts=mav_time(clock) + 120 * UNITS_PER_S)))
    assert len(guard) == 0


def test_frame_for_another_vehicle_is_refused(clock: ManualClock) -> None:
    vehicle_two = MavlinkGuard(KEY, clock=clock, system_id=2)
    with pytest.raises(WrongTargetError, match="system 1"):
        vehicle_two.open(command_frame(*encoder(), target=1))
    vehicle_two.open(command_frame(*encoder(link_id=3), target=2))


def test_reordered_pair_passes_once_each(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock, reorder_window=1_000)
    mav, sink = encoder()
    first, second = command_frame(mav, sink), command_frame(mav, sink)
    guard.open(second)
    guard.open(first)
    for frame in (first, second):
        with pytest.raises(CounterReplayedError):
            guard.open(frame)


def test_allow_listed_id_with_signed_flag_and_bad_signature_dropped(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock, allow_unsigned=frozenset({0}))
    mav, sink = encoder()
    mav.heartbeat_send(6, 8, 0, 0, 0)
    signed = bytearray(sink.frames[-1])
    signed[-1] ^= 0xFF
    with pytest.raises(SignatureInvalidError):
        guard.open(bytes(signed))
    plain = dialect.MAVLink(Sink(), srcSystem=255, srcComponent=190)
    plain.heartbeat_send(6, 8, 0, 0, 0)
    assert not guard.open(plain.file.frames[-1]).signed
    plain.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    with pytest.raises(SignatureRequiredError, match="not allow-listed"):
        guard.open(plain.file.frames[-1])


def test_eviction_fences_old_streams(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock, max_streams=2)
    frames = [command_frame(*encoder(link_id=i, ts=mav_time(clock) + i)) for i in range(3)]
    for frame in frames:
        guard.open(frame)
    assert len(guard) == 2
    with pytest.raises((MessageStaleError, CounterReplayedError)):
        guard.open(frames[0])


def test_refused_new_stream_evicts_no_live_stream(clock: ManualClock) -> None:
    """A new stream at or below the lowest held timestamp of a full table is refused and
    evicts nothing: a live stream keeps its reorder window (review finding 5)."""
    now = mav_time(clock)
    guard = MavlinkGuard(KEY, clock=clock, max_streams=2, reorder_window=1_000)
    a, b = encoder(sysid=200, ts=now + 100), encoder(sysid=201, ts=now + 200)
    late = command_frame(*a)  # now + 101: arrives after a's next frame
    guard.open(command_frame(*a))
    guard.open(command_frame(*b))
    behind = command_frame(*encoder(sysid=202, ts=now + 50))  # a GCS 0.5 ms behind
    with pytest.raises(MessageStaleError, match="lowest mark") as refused:
        guard.open(behind)
    assert refused.value.detail == "fence"
    assert len(guard) == 2
    assert guard.open(late).signed  # still inside a's window: a was not evicted


def test_guard_refuses_its_own_vehicle_as_a_source(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock, system_id=1, allow_unsigned=frozenset({0}))
    mav, sink = encoder(sysid=1)  # a frame the vehicle itself signed
    mav.heartbeat_send(2, 3, 0, 0, 4)
    with pytest.raises(WrongDirectionError):
        guard.open(sink.frames[-1])
    with pytest.raises(WrongDirectionError):
        guard.open(unsigned_heartbeat(sysid=1))
    assert len(guard) == 0  # nothing stamped in the stream table
    guard.open(command_frame(*encoder(sysid=255)))


# --- persistence: lease, flusher, restart fence ------------------------------------------------


class CountingStore:
    """A store wrapper that counts writes (``advance``) and tells frame-path ones apart."""

    def __init__(self, inner: SqliteStore) -> None:
        self.inner = inner
        self.writes: list[str] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def advance(self, key: str, value: int) -> bool:
        self.writes.append(key)
        return self.inner.advance(key, value)


def frames_at(clock: ManualClock, offsets_s: list[float], link_id: int = 1) -> list[bytes]:
    """Signed COMMAND_LONG frames stamped ``offset`` seconds from the clock's now."""
    mav, sink = encoder(link_id=link_id)
    out = []
    for offset in offsets_s:
        mav.signing.timestamp = mav_time(clock) + int(offset * UNITS_PER_S)
        out.append(command_frame(mav, sink))
    return out


def test_restart_fence_refuses_every_capture_after_a_crash(
    tmp_path: Path, clock: ManualClock
) -> None:
    guard = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    captures = frames_at(clock, [-59, -5, 0]) + frames_at(clock, [-1, 0], link_id=2)
    for frame in captures:
        guard.open(frame)
    clock.advance(0.5)  # kill -9: no stop(), nothing flushed, the lease is still held
    restarted = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    with pytest.raises(StateUnavailableError):  # the crashed run's lease has not run out
        restarted.open(frames_at(clock, [0], link_id=3)[0])
    clock.advance(2)
    for frame in captures:
        with pytest.raises((MessageStaleError, CounterReplayedError)) as refused:
            restarted.open(frame)
        assert "restart fence" in str(refused.value)
    assert restarted.open(frames_at(clock, [0])[0]).signed  # the honest sender goes on


def test_honest_sender_continues_right_after_a_clean_restart(
    tmp_path: Path, clock: ManualClock
) -> None:
    guard = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    guard.start()
    captures = frames_at(clock, [-0.2, -0.1, 0])
    for frame in captures:
        guard.open(frame)
    guard.stop()  # flushes, releases the lease at the stop time
    restarted = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    restarted.start()  # the lease was released: claimed at once
    try:
        for frame in captures:
            with pytest.raises((MessageStaleError, CounterReplayedError)):
                restarted.open(frame)
        mav, sink = encoder()
        mav.signing.timestamp = mav_time(clock) + 1  # the very next 10 µs tick
        assert restarted.open(command_frame(mav, sink)).signed
    finally:
        restarted.stop()


def test_sender_that_ran_ahead_raises_the_fence(tmp_path: Path, clock: ManualClock) -> None:
    store = CountingStore(SqliteStore(tmp_path / "mav.db"))
    guard = MavlinkGuard(KEY, clock=clock, store=store)
    ahead = frames_at(clock, [30, 30.5], link_id=7)
    for frame in ahead:
        guard.open(frame)
    assert store.writes.count("mav:high") == 2  # written before each frame that passed it
    clock.advance(3)  # crash, and the lease runs out
    restarted = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    with pytest.raises(MessageStaleError):
        restarted.open(ahead[1])
    with pytest.raises(MessageStaleError):  # a new stream, as far ahead as the fence allows
        restarted.open(frames_at(clock, [25], link_id=8)[0])
    assert restarted.restart_fence >= mav_time(clock) + 27 * UNITS_PER_S
    assert restarted.fenced_until() is not None
    assert restarted.open(frames_at(clock, [29], link_id=9)[0]).signed
    clock.advance(40)  # the wall clock passed every persisted timestamp
    assert restarted.fenced_until() is None


def test_a_previous_versions_ahead_margin_is_migrated_to_a_timestamp(
    tmp_path: Path, clock: ManualClock
) -> None:
    """A state the previous version wrote (a lease and a 13 s ``ahead`` margin): the first
    claim fences as that version did, writes the fence as the highest timestamp, and the
    restart after it no longer adds the margin."""
    store = sqlite_store(tmp_path / "mav.db", clock=clock)
    store.advance("mav:lease", lease_value(2, mav_time(clock)))  # released cleanly now
    store.advance("mav:ahead", 13 * UNITS_PER_S)
    guard = MavlinkGuard(KEY, clock=clock, store=store)
    guard.start()
    fence = guard.restart_fence
    assert fence >= mav_time(clock) + 13 * UNITS_PER_S
    assert store.current("mav:high") == fence
    guard.stop()
    clock.advance(60)
    again = MavlinkGuard(KEY, clock=clock, store=store)
    again.start()
    assert again.fenced_until() is None and again.open(frames_at(clock, [0])[0]).signed
    again.stop()


class Killed(BaseException):
    """The process dies (``kill -9``) at a store write: nothing after it runs."""


class CrashingStore:
    """A store wrapper whose process dies at the first write of ``key`` (before it lands)."""

    def __init__(self, inner: SqliteStore, key: str) -> None:
        self.inner, self.key = inner, key

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def advance(self, key: str, value: int) -> bool:
        if key == self.key:
            raise Killed(key)
        return self.inner.advance(key, value)


@pytest.mark.parametrize("dies_at", ["mav:high", "mav:lease"])
def test_the_ahead_migration_survives_a_kill_between_its_writes(
    tmp_path: Path, clock: ManualClock, dies_at: str
) -> None:
    """A kill (or a failed write) during the first claim of a previous version's state: the
    next start converts ``ahead`` from that version's own lease again, never from a lease
    the dead run wrote, so the old margin is not added to a newer expiry."""
    store = sqlite_store(tmp_path / "mav.db", clock=clock)
    released = mav_time(clock)
    store.advance("mav:lease", lease_value(2, released))
    store.advance("mav:ahead", 13 * UNITS_PER_S)
    dying = MavlinkGuard(KEY, clock=clock, store=CrashingStore(store, dies_at))
    with pytest.raises(Killed):
        dying.start()
    clock.advance(5)  # past any lease the dead run could have claimed
    again = MavlinkGuard(KEY, clock=clock, store=store)
    again.start()
    assert again.restart_fence == released + 13 * UNITS_PER_S
    assert store.current("mav:high") == released + 13 * UNITS_PER_S
    again.stop()


def test_persistence_stays_off_the_frame_path_under_a_burst(
    tmp_path: Path, clock: ManualClock
) -> None:
    """5,000 frames over 5 s on 3 streams, the flusher's tick once a second: the frame path
    writes once (the lease claim), the flusher at most streams + lease per tick."""
    store = CountingStore(SqliteStore(tmp_path / "mav.db"))
    guard = MavlinkGuard(KEY, clock=clock, store=store)
    senders = [encoder(link_id=link) for link in range(3)]
    frame_path = 0
    for i in range(5_000):
        mav, sink = senders[i % 3]
        mav.signing.timestamp = mav_time(clock)
        before = len(store.writes)
        guard.open(command_frame(mav, sink))
        frame_path += len(store.writes) - before
        clock.advance(0.001)
        if i % 1_000 == 999:
            guard.flush()
    assert frame_path == 1
    assert len(store.writes) <= 1 + 5 * (3 + 1)
    assert guard.counts["frame_path_renewals"] == 0


def test_a_late_flusher_makes_the_frame_path_renew_the_lease(
    tmp_path: Path, clock: ManualClock
) -> None:
    store = CountingStore(SqliteStore(tmp_path / "mav.db"))
    guard = MavlinkGuard(KEY, clock=clock, store=store)
    mav, sink = encoder()
    for _ in range(5_000):  # 5 s and no flusher at all: the lease is renewed before it lapses
        mav.signing.timestamp = mav_time(clock)
        guard.open(command_frame(mav, sink))
        clock.advance(0.001)
    assert store.writes.count("mav:lease") <= 1 + 3
    assert guard.counts["frame_path_renewals"] <= 3


def test_second_guard_on_a_store_takes_over_only_behind_the_fence(
    tmp_path: Path, clock: ManualClock
) -> None:
    first = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    second = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    mav, sink = encoder()
    frame = command_frame(mav, sink)
    first.open(frame)
    with pytest.raises(StateUnavailableError):
        second.open(frame)
    clock.advance(3)  # the first guard stalls past its lease; the second takes over
    with pytest.raises(MessageStaleError):
        second.open(frame)
    mav.signing.timestamp = mav_time(clock)
    fresh = command_frame(mav, sink)
    assert second.open(fresh).signed
    with pytest.raises(StateUnavailableError):  # the stalled guard can never renew again
        first.open(command_frame(mav, sink))


def test_write_through_guards_share_a_store_and_accept_each_frame_once(
    tmp_path: Path, clock: ManualClock
) -> None:
    guards = [
        MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"), write_through=True)
        for _ in range(2)
    ]
    mav, sink = encoder()
    for i in range(6):
        frame = command_frame(mav, sink)
        guards[i % 2].open(frame)  # both active at once
        with pytest.raises(CounterReplayedError):
            guards[(i + 1) % 2].open(frame)


def test_store_data_loss_fences_by_the_forward_bound(tmp_path: Path, clock: ManualClock) -> None:
    store = sqlite_store(tmp_path / "mav.db", clock=clock)
    guard = MavlinkGuard(KEY, clock=clock, store=store)
    ahead = frames_at(clock, [40])
    guard.open(ahead[0])
    guard.stop()
    store.close()
    for lost in tmp_path.glob("mav.db*"):
        if not lost.name.endswith(".witness"):
            lost.unlink()  # the lease and the ahead margin go with it; the witness stays
    restarted = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db", clock=clock))
    with pytest.raises(MessageStaleError):
        restarted.open(ahead[0])
    assert restarted.restart_fence >= mav_time(clock) + 60 * UNITS_PER_S


def test_check_records_nothing_and_refuses_what_open_would(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock)
    frame = command_frame(*encoder())
    for _ in range(3):
        assert guard.check(frame).signed  # a check, however often, spends nothing
    assert len(guard) == 0
    guard.open(frame)
    with pytest.raises(CounterReplayedError):
        guard.check(frame)  # the replay is thrown away before the signature is computed


def test_stream_evicted_before_its_flush_stays_fenced(tmp_path: Path, clock: ManualClock) -> None:
    """A stream whose persisted high-water lags what this process accepted (evicted between
    flushes) comes back only above the eviction fence, not above its stale stored value."""
    guard = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"), max_streams=1)
    mav, sink = encoder(link_id=1)
    mav.signing.timestamp = mav_time(clock)
    guard.open(command_frame(mav, sink))
    guard.flush()  # the stream's stored high-water: its first frame
    clock.advance(0.01)
    mav.signing.timestamp = mav_time(clock)
    unflushed = command_frame(mav, sink)
    guard.open(unflushed)
    clock.advance(0.01)
    guard.open(frames_at(clock, [0], link_id=2)[0])  # evicts stream 1 before any flush
    with pytest.raises(MessageStaleError):
        guard.open(unflushed)


def test_admission_of_a_routers_links(clock: ManualClock) -> None:
    """A trusted tool's unsigned v2 frame is signed on its behalf; a frame carrying the
    router's own link id is judged as it is from a trusted link, WRONG_DIRECTION from
    any other (the router signed it for a link no guard commits for)."""
    guard = MavlinkGuard(KEY, clock=clock)
    plain, ours = unsigned_heartbeat(7), command_frame(*encoder(link_id=251))
    assert guard.admit(plain, trusted=True, own_link_id=251) is FrameAdmission.SIGN
    assert guard.admit(ours, trusted=True, own_link_id=251) is FrameAdmission.JUDGE
    assert guard.admit(plain, trusted=False, own_link_id=251) is FrameAdmission.JUDGE
    assert guard.admit(ours, trusted=False, own_link_id=250) is FrameAdmission.JUDGE
    with pytest.raises(WrongDirectionError):
        guard.admit(ours, trusted=False, own_link_id=251)
    assert len(guard) == 0


def test_direction_binding_learns_only_from_signed_frames(clock: ManualClock) -> None:
    """A source system the other side authenticated is refused here from then on; an
    unsigned (allow-listed) frame from the other side teaches nothing."""
    vehicle_side = MavlinkGuard(KEY, clock=clock, allow_unsigned=frozenset({0}))
    ground_side = MavlinkGuard(KEY, clock=clock, allow_unsigned=frozenset({0}))
    ground_side.bind_direction(vehicle_side.open(command_frame(*encoder(sysid=1, link_id=7))))
    ground_side.bind_direction(vehicle_side.open(unsigned_heartbeat(9)))
    with pytest.raises(WrongDirectionError):
        ground_side.open(command_frame(*encoder(sysid=1, link_id=2)))
    assert not ground_side.open(unsigned_heartbeat(9)).signed


def test_a_new_sqlite_store_fences_like_a_memory_one(tmp_path: Path, clock: ManualClock) -> None:
    """A state with no history proves nothing about what ran before: the guard fences
    ``max_forward_s`` from its start, exactly as on a memory store; a restart on the same
    state (its history proven) adds no fence of its own."""
    captured = frames_at(clock, [-1, 0])  # sent before this guard's state began
    memory = MemoryStore(clock=clock)
    on_memory = MavlinkGuard(KEY, clock=clock, store=memory, max_forward_s=5)
    store = SqliteStore(tmp_path / "mav.db", clock=clock)
    on_sqlite = MavlinkGuard(KEY, clock=clock, store=store, max_forward_s=5)
    for guard in (on_memory, on_sqlite):
        for frame in captured:
            with pytest.raises(MessageStaleError, match="restart fence"):
                guard.open(frame)
    assert on_sqlite.restart_fence == on_memory.restart_fence > mav_time(clock)
    clock.advance(5.001)
    assert on_sqlite.open(frames_at(clock, [0], link_id=2)[0]).signed
    on_sqlite.stop()
    store.close()
