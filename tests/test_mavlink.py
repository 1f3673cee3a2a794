"""MAVLink v2 guard and proxy, with real pymavlink ground station and vehicle over UDP loopback."""

from __future__ import annotations

import os
import queue
import random
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

os.environ["MAVLINK20"] = "1"  # pymavlink's mavutil speaks MAVLink 1 unless told otherwise
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay import ManualClock
from antireplay.cli import _signing_key, main
from antireplay.clock import SystemClock
from antireplay.errors import (
    AuthenticationError,
    CounterReplayError,
    InvalidFrameError,
    MessageFromFutureError,
    MessageStaleError,
    NonceExhaustedError,
    StateUnavailableError,
    WrongDirectionError,
)
from antireplay.mavlink import (
    TS_LIMIT,
    UNITS_PER_S,
    MavlinkGuard,
    MavlinkProxy,
    TimestampSource,
    mav_time,
    sign_frame,
)
from antireplay.stores.sqlite import SqliteStore
from tests.conftest import ROOT
from tests.harness import free_port

KEY = bytes(range(32))
NOW = 1_800_000_000.0


class _Sink:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


def encoder(sysid: int = 255, link_id: int = 1, ts: int | None = None) -> tuple[Any, _Sink]:
    """A pymavlink MAVLink object that signs into a list (a GCS without a socket)."""
    sink = _Sink()
    mav = dialect.MAVLink(sink, srcSystem=sysid, srcComponent=190)
    mav.signing.secret_key = KEY
    mav.signing.sign_outgoing = True
    mav.signing.link_id = link_id
    mav.signing.timestamp = mav_time(ManualClock(NOW)) if ts is None else ts
    return mav, sink


def command_frame(mav: Any, sink: _Sink, target: int = 1, param1: float = 1.0) -> bytes:
    mav.command_long_send(target, 1, 400, 0, param1, 0, 0, 0, 0, 0, 0)
    return sink.frames[-1]


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock(wall=NOW)


# --- the guard, directly ------------------------------------------------------------------------


def test_signed_frame_accepted_once(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock, system_id=1)
    frame = command_frame(*encoder())
    assert guard.check(frame).signed
    with pytest.raises(CounterReplayError):
        guard.check(frame)


def test_jamming_frame_changes_nothing(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock)
    mav, sink = encoder()
    guard.check(command_frame(mav, sink))
    jam = bytearray(command_frame(mav, sink))
    jam[-12:-6] = (TS_LIMIT - 1).to_bytes(6, "little")
    with pytest.raises(AuthenticationError):
        guard.check(bytes(jam))
    assert guard.check(command_frame(mav, sink)).signed  # later legitimate frames pass


def test_forged_new_streams_do_not_grow_the_table(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock)
    rng = random.Random(3)
    for _ in range(1_000):
        other = dialect.MAVLink(
            _Sink(), srcSystem=rng.randint(1, 250), srcComponent=rng.randint(1, 250)
        )
        other.signing.secret_key = bytes(32)  # the attacker's key
        other.signing.sign_outgoing = True
        other.signing.link_id = rng.randint(0, 255)
        other.signing.timestamp = mav_time(clock)
        other.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        with pytest.raises(AuthenticationError):
            guard.check(other.file.frames[-1])
    assert len(guard) == 0


def test_new_stream_rule_uses_the_wall_clock(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock)
    old = command_frame(*encoder(ts=mav_time(clock) - 61 * UNITS_PER_S))
    with pytest.raises(MessageStaleError):
        guard.check(old)
    guard.check(command_frame(*encoder(link_id=2, ts=mav_time(clock) - 59 * UNITS_PER_S)))


def test_forward_jump_bound(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock)
    with pytest.raises(MessageFromFutureError):
        guard.check(command_frame(*encoder(ts=mav_time(clock) + 120 * UNITS_PER_S)))
    assert len(guard) == 0


def test_frame_for_another_vehicle_is_refused(clock: ManualClock) -> None:
    vehicle_two = MavlinkGuard(KEY, clock=clock, system_id=2)
    with pytest.raises(AuthenticationError, match="system 1"):
        vehicle_two.check(command_frame(*encoder(), target=1))
    vehicle_two.check(command_frame(*encoder(link_id=3), target=2))


def test_reordered_pair_passes_once_each(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock, reorder_window=1_000)
    mav, sink = encoder()
    first, second = command_frame(mav, sink), command_frame(mav, sink)
    guard.check(second)
    guard.check(first)
    for frame in (first, second):
        with pytest.raises(CounterReplayError):
            guard.check(frame)


def test_allow_listed_id_with_signed_flag_and_bad_signature_dropped(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock, allow_unsigned=frozenset({0}))
    mav, sink = encoder()
    mav.heartbeat_send(6, 8, 0, 0, 0)
    signed = bytearray(sink.frames[-1])
    signed[-1] ^= 0xFF
    with pytest.raises(AuthenticationError):
        guard.check(bytes(signed))
    plain = dialect.MAVLink(_Sink(), srcSystem=255, srcComponent=190)
    plain.heartbeat_send(6, 8, 0, 0, 0)
    assert not guard.check(plain.file.frames[-1]).signed
    plain.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    with pytest.raises(AuthenticationError, match="not allow-listed"):
        guard.check(plain.file.frames[-1])


@pytest.mark.parametrize(
    "bad", [b"", b"\xfd", b"\xfe\x09" + bytes(20), b"\xfd\x09\x00", b"\xfd\x01\x80" + bytes(20)]
)
def test_malformed_frames_are_typed(clock: ManualClock, bad: bytes) -> None:
    with pytest.raises(InvalidFrameError):
        MavlinkGuard(KEY, clock=clock).check(bad)


def test_eviction_fences_old_streams(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock, max_streams=2)
    frames = [command_frame(*encoder(link_id=i, ts=mav_time(clock) + i)) for i in range(3)]
    for frame in frames:
        guard.check(frame)
    assert len(guard) == 2
    with pytest.raises((MessageStaleError, CounterReplayError)):
        guard.check(frames[0])


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
        guard.check(frame)
    clock.advance(0.5)  # kill -9: no stop(), nothing flushed, the lease is still held
    restarted = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    with pytest.raises(StateUnavailableError):  # the crashed run's lease has not run out
        restarted.check(frames_at(clock, [0], link_id=3)[0])
    clock.advance(2)
    for frame in captures:
        with pytest.raises((MessageStaleError, CounterReplayError)) as refused:
            restarted.check(frame)
        assert "restart fence" in str(refused.value)
    assert restarted.check(frames_at(clock, [0])[0]).signed  # the honest sender goes on


def test_honest_sender_continues_right_after_a_clean_restart(
    tmp_path: Path, clock: ManualClock
) -> None:
    guard = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    guard.start()
    captures = frames_at(clock, [-0.2, -0.1, 0])
    for frame in captures:
        guard.check(frame)
    guard.stop()  # flushes, releases the lease at the stop time
    restarted = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    restarted.start(wait_s=0)  # no waiting: the lease was released
    try:
        for frame in captures:
            with pytest.raises((MessageStaleError, CounterReplayError)):
                restarted.check(frame)
        mav, sink = encoder()
        mav.signing.timestamp = mav_time(clock) + 1  # the very next 10 µs tick
        assert restarted.check(command_frame(mav, sink)).signed
    finally:
        restarted.stop()


def test_sender_that_ran_ahead_raises_the_fence(tmp_path: Path, clock: ManualClock) -> None:
    store = CountingStore(SqliteStore(tmp_path / "mav.db"))
    guard = MavlinkGuard(KEY, clock=clock, store=store)
    ahead = frames_at(clock, [30, 30.5], link_id=7)
    for frame in ahead:
        guard.check(frame)
    assert store.writes.count("mav:ahead") == 2  # written before each frame that exceeded it
    clock.advance(3)  # crash, and the lease runs out
    restarted = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db"))
    with pytest.raises(MessageStaleError):
        restarted.check(ahead[1])
    with pytest.raises(MessageStaleError):  # a new stream, as far ahead as the fence allows
        restarted.check(frames_at(clock, [25], link_id=8)[0])
    assert restarted.restart_fence >= mav_time(clock) + 28 * UNITS_PER_S
    assert restarted.check(frames_at(clock, [31], link_id=9)[0]).signed


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
        guard.check(command_frame(mav, sink))
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
        guard.check(command_frame(mav, sink))
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
    first.check(frame)
    with pytest.raises(StateUnavailableError):
        second.check(frame)
    clock.advance(3)  # the first guard stalls past its lease; the second takes over
    with pytest.raises(MessageStaleError):
        second.check(frame)
    mav.signing.timestamp = mav_time(clock)
    fresh = command_frame(mav, sink)
    assert second.check(fresh).signed
    with pytest.raises(StateUnavailableError):  # the stalled guard can never renew again
        first.check(command_frame(mav, sink))


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
        guards[i % 2].check(frame)  # both active at once
        with pytest.raises(CounterReplayError):
            guards[(i + 1) % 2].check(frame)


def test_store_data_loss_fences_by_the_forward_bound(tmp_path: Path, clock: ManualClock) -> None:
    store = SqliteStore(tmp_path / "mav.db", clock=clock)
    guard = MavlinkGuard(KEY, clock=clock, store=store)
    ahead = frames_at(clock, [40])
    guard.check(ahead[0])
    guard.stop()
    store.close()
    for lost in tmp_path.glob("mav.db*"):
        if not lost.name.endswith(".witness"):
            lost.unlink()  # the lease and the ahead margin go with it; the witness stays
    restarted = MavlinkGuard(KEY, clock=clock, store=SqliteStore(tmp_path / "mav.db", clock=clock))
    with pytest.raises(MessageStaleError):
        restarted.check(ahead[0])
    assert restarted.restart_fence >= mav_time(clock) + 60 * UNITS_PER_S


def test_timestamp_source_tracks_time_and_refuses_wrap(clock: ManualClock) -> None:
    source = TimestampSource(clock)
    a, b = source.next(), source.next()
    assert a == mav_time(clock) and b == a + 1
    clock.advance(1)
    assert source.next() == mav_time(clock)
    with pytest.raises(NonceExhaustedError):
        TimestampSource(clock, last=TS_LIMIT - 1).next()


def test_sign_frame_is_accepted_by_guard_and_pymavlink(clock: ManualClock) -> None:
    plain = dialect.MAVLink(_Sink(), srcSystem=255, srcComponent=190)
    plain.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    signed = sign_frame(plain.file.frames[-1], KEY, 4, TimestampSource(clock))
    assert MavlinkGuard(KEY, clock=clock).check(signed).stream == (255, 190, 4)
    receiver = dialect.MAVLink(_Sink())
    receiver.signing.secret_key = KEY
    receiver.signing.timestamp = mav_time(clock)
    assert receiver.check_signature(bytearray(signed), 255, 190)
    with pytest.raises(AuthenticationError):  # the signature binds the key: another one fails
        MavlinkGuard(bytes(reversed(KEY)), clock=clock).check(signed)


# --- the proxy with real pymavlink endpoints --------------------------------------------------


class Rig:
    """GCS (pymavlink, signing) -> proxy -> vehicle (pymavlink, observing everything)."""

    def __init__(
        self,
        system_id: int = 1,
        *,
        bind_system_id: bool = True,
        allow_unsigned: frozenset[int] = frozenset(),
    ) -> None:
        vport = free_port()
        self.vehicle = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{vport}", source_system=system_id, source_component=1
        )
        self.rejections: queue.Queue[tuple[str, str]] = queue.Queue()
        self.proxy = MavlinkProxy(
            ("127.0.0.1", 0),
            ("127.0.0.1", vport),
            MavlinkGuard(
                KEY,
                system_id=system_id if bind_system_id else None,
                allow_unsigned=allow_unsigned,
            ),
            MavlinkGuard(KEY),
            lambda direction, exc, _raw: self.rejections.put((direction, str(exc.code))),
        )
        self.proxy.start()
        host, port = self.proxy.address
        self.gcs = mavutil.mavlink_connection(
            f"udpout:{host}:{port}", source_system=255, source_component=190
        )
        self.gcs.setup_signing(KEY, sign_outgoing=True, link_id=1)
        self.raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def send_command(self, param1: float, target: int = 1) -> bytes:
        msg = self.gcs.mav.command_long_encode(target, 1, 400, 0, param1, 0, 0, 0, 0, 0, 0)
        self.gcs.mav.send(msg)
        return bytes(msg.get_msgbuf())

    def inject(self, raw: bytes) -> None:
        self.raw.sendto(raw, self.proxy.address)

    def commands_until(self, sentinel: float) -> list[float]:
        """Every COMMAND_LONG param1 the vehicle received, up to and including the sentinel."""
        seen: list[float] = []
        while True:
            msg = self.vehicle.recv_match(type="COMMAND_LONG", blocking=True, timeout=10)
            assert msg is not None, f"sentinel {sentinel} never arrived; got {seen}"
            seen.append(float(msg.param1))
            if msg.param1 == sentinel:
                return seen

    def rejected(self) -> tuple[str, str]:
        """The next rejection the proxy reported (direction, code); the proxy calls back."""
        try:
            return self.rejections.get(timeout=10)
        except queue.Empty:
            pytest.fail("the proxy reported no rejection")

    def close(self) -> None:
        self.proxy.stop()
        self.gcs.close()
        self.vehicle.close()
        self.raw.close()


@pytest.fixture
def rig() -> Iterator[Rig]:
    made = Rig()
    yield made
    made.close()


def test_command_arrives_once_and_exact_replay_is_dropped(rig: Rig) -> None:
    captured = rig.send_command(1.0)
    assert rig.commands_until(1.0) == [1.0]
    rig.inject(captured)
    rig.send_command(2.0)
    assert rig.commands_until(2.0) == [2.0]
    assert rig.proxy.stats.dropped["inbound:COUNTER_REPLAYED"] == 1


def test_jamming_through_the_proxy(rig: Rig) -> None:
    frame = bytearray(rig.send_command(1.0))
    rig.commands_until(1.0)
    frame[-12:-6] = (TS_LIMIT - 1).to_bytes(6, "little")
    rig.inject(bytes(frame))
    rig.send_command(2.0)
    assert rig.commands_until(2.0) == [2.0]
    assert rig.proxy.stats.dropped["inbound:SIGNATURE_INVALID"] == 1


def test_thousand_forged_streams_through_the_proxy(rig: Rig) -> None:
    rig.send_command(1.0)
    rig.commands_until(1.0)
    before = len(rig.proxy.inbound)
    rng = random.Random(11)
    for _ in range(1_000):
        forger = dialect.MAVLink(
            _Sink(), srcSystem=rng.randint(1, 250), srcComponent=rng.randint(1, 250)
        )
        forger.signing.secret_key = os.urandom(32)
        forger.signing.sign_outgoing = True
        forger.signing.link_id = rng.randint(0, 255)
        forger.signing.timestamp = mav_time(ManualClock(time.time()))
        forger.command_long_send(1, 1, 400, 0, 9.0, 0, 0, 0, 0, 0, 0)
        rig.inject(forger.file.frames[-1])
    rig.send_command(2.0)
    assert rig.commands_until(2.0) == [2.0]
    assert len(rig.proxy.inbound) == before


def test_malformed_datagrams_counted_and_dropped(rig: Rig) -> None:
    for bad in (b"\xfd\x05", b"hello", bytes(3), b"\xfd\x09\x00\x00\x01\xff\xbe\x4c\x00\x00"):
        rig.inject(bad)
    rig.send_command(3.0)
    assert rig.commands_until(3.0) == [3.0]
    assert rig.proxy.stats.dropped["inbound:INVALID_FRAME"] == 4


def test_replay_towards_a_second_vehicle_is_dropped(rig: Rig) -> None:
    captured = rig.send_command(1.0, target=1)
    rig.commands_until(1.0)
    second = Rig(system_id=2)
    try:
        second.inject(captured)
        second.send_command(5.0, target=2)
        assert second.commands_until(5.0) == [5.0]
        assert second.proxy.stats.dropped["inbound:SIGNATURE_INVALID"] == 1
    finally:
        second.close()


def test_round_trip_both_directions_with_signing_everywhere() -> None:
    rig = Rig()
    try:
        rig.vehicle.setup_signing(KEY, sign_outgoing=True, link_id=7)
        rig.send_command(1.0)
        assert rig.commands_until(1.0) == [1.0]
        rig.vehicle.mav.heartbeat_send(2, 3, 0, 0, 4)
        reply = rig.gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=10)
        assert reply is not None and reply.get_srcSystem() == 1
        assert rig.proxy.stats.forwarded["outbound"] >= 1
    finally:
        rig.close()


def any_id(_mav: object, _msgid: int) -> bool:
    """pymavlink's hook: the vehicle takes unsigned frames (the proxy's allow-list decides)."""
    return True


def unsigned_heartbeat(sysid: int) -> bytes:
    plain = dialect.MAVLink(_Sink(), srcSystem=sysid, srcComponent=1)
    plain.heartbeat_send(6, 8, 0, 0, 0)
    return bytes(plain.file.frames[-1])


def forged_command() -> bytes:
    forger = dialect.MAVLink(_Sink(), srcSystem=255, srcComponent=190)
    forger.signing.secret_key = bytes(32)  # not the link key
    forger.signing.sign_outgoing = True
    forger.signing.link_id = 1
    forger.signing.timestamp = mav_time(ManualClock(time.time()))
    forger.command_long_send(1, 1, 400, 0, 9.0, 0, 0, 0, 0, 0, 0)
    return bytes(forger.file.frames[-1])


@pytest.mark.parametrize("attack", ["garbage", "forged", "replayed", "unsigned-allow-listed"])
def test_unauthenticated_datagram_cannot_steal_telemetry(attack: str) -> None:
    """One datagram from an attacker's address must not move the ground peer."""
    rig = Rig(allow_unsigned=frozenset({0}))  # HEARTBEAT may come unsigned
    try:
        rig.vehicle.setup_signing(
            KEY, sign_outgoing=True, link_id=7, allow_unsigned_callback=any_id
        )
        captured = rig.send_command(1.0)
        assert rig.commands_until(1.0) == [1.0]
        gcs_address = ("127.0.0.1", rig.gcs.port.getsockname()[1])
        assert rig.proxy.peer == gcs_address
        if attack == "unsigned-allow-listed":
            rig.inject(unsigned_heartbeat(sysid=200))
            got = rig.vehicle.recv_match(type="HEARTBEAT", blocking=True, timeout=10)
            assert got is not None and got.get_srcSystem() == 200  # forwarded, by policy
        else:
            datagram = {"garbage": b"hello", "forged": forged_command(), "replayed": captured}
            rig.inject(datagram[attack])
            code = {"garbage": "INVALID_FRAME", "forged": "SIGNATURE_INVALID"}
            assert rig.rejected() == ("inbound", code.get(attack, "COUNTER_REPLAYED"))
        assert rig.proxy.peer == gcs_address
        rig.vehicle.mav.heartbeat_send(2, 3, 0, 0, 4)  # telemetry, signed by the vehicle
        reply = rig.gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=10)
        assert reply is not None and reply.get_srcSystem() == 1
        rig.raw.setblocking(False)
        with pytest.raises(BlockingIOError):
            rig.raw.recv(65_535)  # the attacker received nothing
    finally:
        rig.close()


def test_no_telemetry_before_a_ground_station_authenticated() -> None:
    rig = Rig(allow_unsigned=frozenset({0}))
    try:
        rig.vehicle.setup_signing(
            KEY, sign_outgoing=True, link_id=7, allow_unsigned_callback=any_id
        )
        rig.inject(unsigned_heartbeat(sysid=200))  # an unsigned frame teaches no peer
        assert rig.vehicle.recv_match(type="HEARTBEAT", blocking=True, timeout=10) is not None
        assert rig.proxy.peer is None
        rig.send_command(1.0)
        assert rig.commands_until(1.0) == [1.0]
        assert rig.proxy.peer == ("127.0.0.1", rig.gcs.port.getsockname()[1])
    finally:
        rig.close()


def test_guard_refuses_its_own_vehicle_as_a_source(clock: ManualClock) -> None:
    guard = MavlinkGuard(KEY, clock=clock, system_id=1, allow_unsigned=frozenset({0}))
    mav, sink = encoder(sysid=1)  # a frame the vehicle itself signed
    mav.heartbeat_send(2, 3, 0, 0, 4)
    with pytest.raises(WrongDirectionError):
        guard.check(sink.frames[-1])
    with pytest.raises(WrongDirectionError):
        guard.check(unsigned_heartbeat(sysid=1))
    assert len(guard) == 0  # nothing stamped in the stream table
    guard.check(command_frame(*encoder(sysid=255)))


@pytest.mark.parametrize("bind_system_id", [True, False])
def test_reflected_vehicle_frame_is_dropped_with_a_typed_code(bind_system_id: bool) -> None:
    """A signed frame the vehicle sent, sent back to the listen port, never reaches it."""
    rig = Rig(bind_system_id=bind_system_id)
    try:
        rig.vehicle.setup_signing(KEY, sign_outgoing=True, link_id=7)
        rig.send_command(1.0)
        assert rig.commands_until(1.0) == [1.0]
        rig.vehicle.mav.command_long_send(255, 190, 400, 0, 7.0, 0, 0, 0, 0, 0, 0)
        reply = rig.gcs.recv_match(type="COMMAND_LONG", blocking=True, timeout=10)
        assert reply is not None and reply.get_srcSystem() == 1
        rig.inject(bytes(reply.get_msgbuf()))  # reflected to the ground side
        assert rig.rejected() == ("inbound", "WRONG_DIRECTION")
        rig.send_command(2.0)
        assert rig.commands_until(2.0) == [2.0]  # the reflected 7.0 never arrived
        assert rig.proxy.stats.forwarded["inbound"] == 2
    finally:
        rig.close()


def test_ground_frame_echoed_by_the_vehicle_side_is_dropped() -> None:
    """Radios and routers that echo: a ground frame coming back never reaches the ground."""
    rig = Rig()
    try:
        captured = rig.send_command(1.0)
        assert rig.commands_until(1.0) == [1.0]
        rig.vehicle.write(captured)  # the vehicle side sends the ground station's frame back
        assert rig.rejected() == ("outbound", "WRONG_DIRECTION")
        assert rig.proxy.stats.forwarded["outbound"] == 0
    finally:
        rig.close()


class _UdpWriter:
    """pymavlink's output file: each packed frame goes out as one datagram, and is kept."""

    def __init__(self, to: tuple[str, int]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.to = to
        self.sent: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.sent.append(bytes(data))
        self.sock.sendto(data, self.to)


def _paced(count: int, hz: float, send: Any) -> None:
    """Call ``send(i)`` ``count`` times at ``hz`` (a load generator's pacing, not a wait)."""
    start = time.perf_counter()
    for i in range(count):
        delay = start + i / hz - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        send(i)


def _dropped(metrics_port: int) -> dict[str, float]:
    with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=10) as reply:
        text = reply.read().decode()
    found = {}
    for line in text.splitlines():
        if line.startswith("antireplay_mavlink_dropped_total{"):
            labels, _, value = line.rpartition(" ")
            found[labels.split('code="')[1].split('"')[0]] = float(value)
    return found


def _until_dropped(metrics_port: int, count: int) -> None:
    """Poll the proxy's metrics until it has refused ``count`` frames (fail after 20 s)."""
    deadline = time.monotonic() + 20
    while sum(_dropped(metrics_port).values()) < count:
        if time.monotonic() > deadline:
            pytest.fail(f"the proxy judged fewer than {count} replays: {_dropped(metrics_port)}")
        time.sleep(0.02)


SENTINEL_MS = 4_000_000_000


def test_cli_proxy_kill_9_at_1000_hz_then_every_capture_dropped(tmp_path: Path) -> None:
    """A real proxy on its default SQLite store, signed ATTITUDE at 1,000 Hz from pymavlink,
    SIGKILL mid-stream, restart, replay every capture: all dropped; the sender goes on."""
    key_file = tmp_path / "key.hex"
    key_file.write_text(KEY.hex())
    vport, pport, mport = free_port(), free_port(), free_port()
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", vport))
    vehicle.settimeout(0.2)
    received: list[bytes] = []
    sentinel_seen, closing = threading.Event(), threading.Event()

    def vehicle_loop() -> None:
        while not closing.is_set():
            try:
                datagram = vehicle.recv(65_535)
            except TimeoutError:
                continue
            received.append(datagram)
            if int.from_bytes(datagram[10:14], "little") == SENTINEL_MS:
                sentinel_seen.set()

    args = [
        sys.executable, "-m", "antireplay", "mavlink-proxy", "--listen", f"udp:127.0.0.1:{pport}",
        "--forward", f"udp:127.0.0.1:{vport}", "--key-file", str(key_file), "--system-id", "1",
        "--store", f"sqlite:{tmp_path / 'mav.db'}", "--audit", str(tmp_path / "audit.db"),
        "--metrics-port", str(mport),
    ]  # fmt: skip
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))

    def start() -> subprocess.Popen[bytes]:
        proc = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert proc.stdout is not None
        if b"mavlink-proxy" not in proc.stdout.readline():  # listening
            pytest.fail(f"the proxy did not start: {proc.communicate()[1].decode()}")
        return proc

    out = _UdpWriter(("127.0.0.1", pport))
    gcs = dialect.MAVLink(out, srcSystem=255, srcComponent=190)
    gcs.signing.secret_key, gcs.signing.sign_outgoing, gcs.signing.link_id = KEY, True, 1
    wall = SystemClock()

    def send(time_boot_ms: int) -> None:
        """Wall-anchored, as the spec asks (pymavlink alone only adds 1 per frame)."""
        gcs.signing.timestamp = max(gcs.signing.timestamp, mav_time(wall))
        gcs.attitude_send(time_boot_ms, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0)

    receiver = threading.Thread(target=vehicle_loop)
    receiver.start()
    proxy = start()
    try:

        def attitude(i: int) -> None:
            send(i + 1)
            if i == 1_500:
                proxy.send_signal(signal.SIGKILL)  # mid-stream

        _paced(2_000, 1_000, attitude)
        proxy.wait()
        forwarded_before = len(received)
        assert forwarded_before >= 1_000, forwarded_before  # the stream was flowing
        captures = list(out.sent)
        proxy = start()
        raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for batch in range(0, len(captures), 100):  # each batch judged before the next one
            size = min(100, len(captures) - batch)
            _paced(size, 1_000, lambda i, at=batch: raw.sendto(captures[at + i], out.to))
            _until_dropped(mport, batch + size)
        raw.close()
        _paced(50, 1_000, lambda i: send(10_000 + i))
        send(SENTINEL_MS)
        if not sentinel_seen.wait(10):
            pytest.fail("the honest sender's frames never passed the restarted proxy")
        after = received[forwarded_before:]
        assert not set(after) & set(captures)  # not one capture got through
        assert len(after) == 51  # every fresh frame did
        dropped = _dropped(mport)
        assert sum(dropped.values()) == len(captures), dropped
        assert set(dropped) <= {"MESSAGE_STALE", "COUNTER_REPLAYED"}, dropped
    finally:
        proxy.terminate()
        proxy.wait()
        closing.set()
        receiver.join()
        vehicle.close()
        out.sock.close()


def test_signing_key_file_forms(tmp_path: Path) -> None:
    raw = tmp_path / "raw.key"
    raw.write_bytes(b"\n" + bytes(range(1, 31)) + b" ")  # a raw key may start/end with whitespace
    assert _signing_key(raw) == b"\n" + bytes(range(1, 31)) + b" "
    hexed = tmp_path / "hex.key"
    hexed.write_text(KEY.hex() + "\n")
    assert _signing_key(hexed) == KEY


@pytest.mark.parametrize("content", [None, b"", b"zz" * 32, b"\xff" * 64, b"0" * 63])
def test_cli_proxy_refuses_a_bad_key_file_naming_it(tmp_path: Path, content: bytes | None) -> None:
    key = tmp_path / "link.key"
    if content is None:
        key.mkdir()  # a directory where the key should be
    else:
        key.write_bytes(content)
    result = CliRunner().invoke(main, [
        "mavlink-proxy", "--listen", "udp:127.0.0.1:9", "--forward", "udp:127.0.0.1:9",
        "--key-file", str(key), "--audit", str(tmp_path / "audit.db"),
    ])  # fmt: skip
    assert result.exit_code == 2
    said = " ".join(result.output.split())
    assert str(key) in said and "Traceback" not in said
    assert not (tmp_path / "audit.db").exists()
