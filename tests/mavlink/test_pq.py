"""The post-quantum MAVLink carriage, sans I/O: dialect, chunks, reassembly, the two ends."""

from __future__ import annotations

import contextlib
import importlib.util
import os
import random
import secrets
import struct
from pathlib import Path

import pytest
from cryptography.hazmat.primitives.asymmetric import x25519
from hypothesis import given, settings
from hypothesis import strategies as st

from antireplay import ManualClock
from antireplay.core.counters import NonceCounter
from antireplay.core.errors import (
    CounterReplayedError,
    InvalidFrameError,
    ReplayAttackError,
    SignatureInvalidError,
)
from antireplay.mavlink.codec import parse_frame
from antireplay.mavlink.pq import (
    CHUNK_DATA,
    DIALECT,
    MAX_CHUNKS,
    MSG_CHUNK,
    MSG_REPAIR,
    ChunkKind,
    ChunkSender,
    GroundEnd,
    Reassembler,
    VehicleEnd,
    chunk_key,
    compact,
    inner_of,
    open_compact,
    pack_v2,
    parse_chunk,
)
from antireplay.mavlink.pq.link import PqLink, SessionEvent
from antireplay.mavlink.router import FrameRefusal
from antireplay.pq.session import REKEY_AFTER, Initiator, Purpose, Responder
from antireplay.pq.session import Direction as Dir
from antireplay.pq.session import Opened as Open
from antireplay.pq.session import Session as Sess

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as dialect
from pymavlink.generator import mavgen

from harness import until
from harness.mavlink_frames import FakeTransport
from harness.pq_ends import (
    ARM,
    FAST_AIR_BPS,
    GCS_KEY,
    ROBOT_KEM,
    EndPair,
    Keep,
    arm,
    connected,
    plain,
    raw_chunk,
)


@pytest.fixture
def link(clock: ManualClock) -> EndPair:
    """Both ends, hand-shaken, the session proven by vehicle traffic (its budget full)."""
    made = connected(clock)
    made.down(made.vehicle.from_local(plain(lambda m: m.heartbeat_send(2, 3, 0, 0, 4), sysid=1)))
    made.telemetry.clear()
    return made


def test_dialect_xml_crc_extras_and_pymavlink_decodes_our_chunks(tmp_path: Path) -> None:
    """The published XML generates a pymavlink dialect that decodes what we send."""
    xml = Path(__file__).parents[2] / "src/antireplay/mavlink/antireplay_pq.xml"
    opts = mavgen.Opts(str(tmp_path / "pqdialect.py"), wire_protocol="2.0", language="Python3")
    assert mavgen.mavgen(opts, [str(xml)])
    spec = importlib.util.spec_from_file_location("pqdialect", tmp_path / "pqdialect.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.mavlink_map[MSG_CHUNK].crc_extra == DIALECT[MSG_CHUNK][0]
    frames = ChunkSender(255, 197).frames(bytes(range(256)) * 2, ChunkKind.HS1)
    decoder = module.MAVLink(Keep())
    decoded = [decoder.decode(bytearray(raw)) for raw in frames]
    assert [(m.index, m.count, m.kind) for m in decoded] == [
        (0, 3, 0x11), (1, 3, 0x11), (2, 3, 0x11), (3, 3, 0x11),
    ]  # fmt: skip
    assert b"".join(bytes(m.data[: m.len]) for m in decoded[:3]) == bytes(range(256)) * 2
    assert module.mavlink_map[MSG_REPAIR].crc_extra == DIALECT[MSG_REPAIR][0]


def test_arm_arrives_once_and_its_replay_is_dropped(link: EndPair) -> None:
    frames = link.ground.from_local(arm())
    assert len(frames) == 22  # 4,627-byte ML-DSA-87 signature: 20 chunks, and 2 parity
    link.up(frames)
    (command,) = link.commands()
    assert (command.command, command.target_system, command.param1) == (ARM, 1, 1.0)
    assert command.get_srcSystem() == 255 and command.get_srcComponent() == 190
    assert link.vehicle.reassembly.late == 3 + 2  # parity after a whole HS1, command: unused
    link.up(frames)  # the whole capture again: each chunk's transfer already opened
    assert len(link.commands()) == 1
    assert link.refused == ["REPLAY_DETECTED"] * 22


def test_telemetry_both_ways_is_hmac_in_one_chunk(link: EndPair) -> None:
    beat = plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4))
    (frame,) = link.ground.from_local(beat)  # a GCS heartbeat: data purpose, one chunk
    link.up([frame])
    assert link.delivered == [beat]  # byte for byte
    attitude = plain(lambda m: m.attitude_send(1, 0.1, 0.2, 0.3, 0, 0, 0), sysid=1)
    air = link.vehicle.from_local(attitude)
    assert len(air) == 1
    link.down(air)
    assert link.telemetry == [attitude]
    link.down(air)  # replayed telemetry
    assert link.telemetry == [attitude] and link.refused == ["COUNTER_REPLAYED"]


def test_capture_from_a_previous_session_is_dropped(link: EndPair) -> None:
    old = link.ground.from_local(arm())
    link.up(old)
    link.ground = link.new_ground()  # the ground end restarts: a new session
    link.connect()
    link.up(old)
    assert len(link.commands()) == 1
    link.up(link.ground.from_local(arm(param1=0.0)))
    assert [c.param1 for c in link.commands()] == [1.0, 0.0]


def test_reordered_duplicated_chunks_deliver_once(link: EndPair) -> None:
    frames = link.ground.from_local(arm())
    shuffled = frames + frames[:5]
    random.Random(7).shuffle(shuffled)
    link.up(shuffled)
    assert len(link.commands()) == 1
    # the last index came early: the rest was asked for at once; what came after is a replay
    assert set(link.refused) <= {"REPLAY_DETECTED"}


def test_a_lost_chunk_costs_that_chunk_not_the_command(link: EndPair, clock: ManualClock) -> None:
    first = link.ground.from_local(arm(param1=1.0))
    link.up(first[:7] + first[8:])  # chunk 7 lost: its parity group rebuilds it
    assert link.vehicle.reassembly.rebuilt == 1 and link.ground.repairs["resent"] == 0
    second = link.ground.from_local(arm(param1=0.0))
    # chunks 7 and 9 lost (one parity group): the last chunk's arrival asks for one of them
    link.up(second[:7] + second[8:9] + second[10:])
    assert link.ground.repairs == {"resent": 1} and link.vehicle.repairs == {"nack_sent": 1}
    assert [c.param1 for c in link.commands()] == [1.0, 0.0]
    third = link.ground.from_local(arm(param1=2.0))
    nack = link.vehicle.from_air  # every repair lost: the transfer expires, counted
    for raw in third[:7] + third[8:9] + third[10:]:
        nack(raw)
    clock.advance(11)
    link.up(link.ground.from_local(arm(param1=3.0)))
    assert [c.param1 for c in link.commands()] == [1.0, 0.0, 3.0]
    assert link.vehicle.reassembly.expired == 1


def _tamper(raw: bytes, at: int, value: int) -> bytes:
    """Rewrite one payload byte and fix the MAVLink CRC (a man in the middle would)."""
    frame = parse_frame(raw)
    payload = bytearray(frame.payload.ljust(DIALECT[MSG_CHUNK][1], b"\0"))
    payload[at] = value
    return pack_v2(
        MSG_CHUNK,
        bytes(payload),
        DIALECT[MSG_CHUNK][0],
        sysid=frame.sysid,
        compid=frame.compid,
        seq=0,
    )


def test_mitm_rewriting_target_msgid_or_splicing_gains_nothing(link: EndPair) -> None:
    # the target system sits in the first chunk: chunk header, compact header, inner header,
    # then COMMAND_LONG's target_system at payload offset 30
    target_at = 6 + 10 + 6 + 30
    frames = link.ground.from_local(arm(target=1))
    link.up([_tamper(frames[0], target_at, 2), *frames[1:]])
    assert link.refused == ["SIGNATURE_INVALID"]  # the chunk MAC; parity rebuilt the genuine
    assert [c.target_system for c in link.commands()] == [1]
    # another message id in the outer header: the CRC extra no longer matches
    header = bytearray(link.ground.from_local(arm(param1=5.0))[0])
    header[7] = dialect.MAVLINK_MSG_ID_COMMAND_LONG & 0xFF
    link.up([bytes(header)])
    assert link.refused[-1] == "INVALID_FRAME"
    # splice: the chunks of two commands, the second renumbered to the first's transfer
    first, second = link.ground.from_local(arm(param1=1.0)), link.ground.from_local(arm(param1=0.0))
    transfer = struct.unpack_from("<H", parse_frame(first[0]).payload)[0]
    renumbered = [_tamper(_tamper(raw, 0, transfer & 0xFF), 1, transfer >> 8) for raw in second]
    link.refused.clear()
    link.up(first[:10] + renumbered[10:])
    assert len(link.commands()) == 1 and link.refused == ["SIGNATURE_INVALID"] * 12
    # an insider holding the session's HMAC keys rewrites the target: ML-DSA-87 still fails
    session = link.ground.session
    assert session is not None
    blob = bytearray(session.seal(inner_of(parse_frame(arm(target=1))), Purpose.COMMAND))
    blob[28 + 6 + 30] = 2
    key = chunk_key(session.send_key)
    link.up(ChunkSender(255, 197, transfer=900).frames(compact(bytes(blob)), ChunkKind.FRAME, key))
    assert link.refused[-1] == "SIGNATURE_INVALID" and len(link.commands()) == 1


def test_chunk_flood_cannot_crowd_out_a_command(link: EndPair) -> None:
    rng = random.Random(3)
    flood = []
    for transfer in range(500):  # session-frame chunks with made-up MACs: refused unbuffered
        fields = (transfer, 0, 20, CHUNK_DATA, ChunkKind.FRAME_CHUNKED)
        flood.append(raw_chunk(fields, rng.randbytes(CHUNK_DATA)))
    frames = link.ground.from_local(arm())
    mixed = frames[:10] + flood + frames[10:]
    link.up(mixed)
    assert len(link.commands()) == 1
    assert link.refused.count("SIGNATURE_INVALID") == 500


def test_memory_is_bounded(clock: ManualClock) -> None:
    reassembler = Reassembler(clock=clock)
    sender = ChunkSender(9, 9)
    for _ in range(50):
        for raw in sender.frames(os.urandom(31 * CHUNK_DATA), ChunkKind.HS1)[:-1]:
            reassembler.feed(parse_chunk(parse_frame(raw)))
    assert reassembler.buffered <= 2 * MAX_CHUNKS * CHUNK_DATA


@pytest.mark.parametrize(
    ("fields", "why"),
    [
        ((1, 3, 3, 10, 1), "chunk 3 of 3"),
        ((1, 0, 33, 10, 1), "at most 32"),
        ((1, 0, 2, 250, 1), "length"),
        ((1, 0, 2, 8, 4), "length"),
        ((1, 0, 2, 10, 3), "one chunk"),
        ((1, 0, 1, 10, 1), "several chunks"),
        ((1, 0, 1, 10, 9), "unknown chunk kind"),
    ],
)
def test_chunk_bounds(fields: tuple[int, ...], why: str) -> None:
    raw = raw_chunk(fields, b"\x01" * CHUNK_DATA)
    with pytest.raises(InvalidFrameError, match=why):
        parse_chunk(parse_frame(raw))


def test_rekey_before_the_counter_limit(link: EndPair) -> None:
    session = link.ground.session
    assert session is not None
    session._send[Purpose.DATA] = NonceCounter(REKEY_AFTER)
    out = link.ground.from_local(plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4)))
    assert len(out) > 1  # the frame and a new HS1
    link.up(out)
    assert link.ground.session is not session
    link.up(link.ground.from_local(arm()))
    assert len(link.commands()) == 1


@settings(max_examples=1_000, deadline=None)
@given(st.binary(max_size=280))
def test_fuzzed_air_frames_raise_only_typed_errors(data: bytes) -> None:
    with contextlib.suppress(ReplayAttackError):
        FUZZ.vehicle.from_air(data)
    with contextlib.suppress(ReplayAttackError):
        FUZZ.ground.from_air(data)


@settings(max_examples=300, deadline=None)
@given(st.binary(min_size=CHUNK_DATA + 6, max_size=CHUNK_DATA + 6))
def test_fuzzed_chunk_payloads_raise_only_typed_errors(payload: bytes) -> None:
    raw = pack_v2(MSG_CHUNK, payload, DIALECT[MSG_CHUNK][0], sysid=255, compid=197, seq=0)
    with contextlib.suppress(ReplayAttackError):
        FUZZ.vehicle.from_air(raw)


FUZZ = EndPair(ManualClock())
FUZZ.connect()


def test_hybrid_ends_carry_arm_once(clock: ManualClock) -> None:
    vehicle_x25519 = x25519.X25519PrivateKey.generate()
    link = EndPair(clock)
    link.responder = Responder(
        ROBOT_KEM, {"gcs": GCS_KEY.public_key()}, clock=clock, x25519_key=vehicle_x25519
    )
    link.vehicle = VehicleEnd(link.responder, clock=clock)
    initiator = Initiator("gcs", GCS_KEY, clock)
    hybrid = vehicle_x25519.public_key()
    link.ground = GroundEnd(initiator, ROBOT_KEM.public_key(), hybrid=hybrid, clock=clock)
    hs1 = link.ground.handshake()
    assert len(hs1) == 29  # the X25519 share fits in the same 26 chunks (and 3 parity)
    link.up(hs1)
    frames = link.ground.from_local(arm())
    link.up(frames + frames)
    assert len(link.commands()) == 1 and link.refused == ["REPLAY_DETECTED"] * 22


def test_a_frame_withheld_from_a_superseded_session_never_plays(link: EndPair) -> None:
    withheld = link.ground.from_local(arm(param1=1.0))  # jammed and recorded, never delivered
    link.connect()  # the ground end rekeys
    link.up(link.ground.from_local(arm(param1=0.0)))  # the new session carries a frame
    link.up(withheld)
    assert [c.param1 for c in link.commands()] == [0.0]
    assert link.refused[-20:] == ["SIGNATURE_INVALID"] * 20  # no live session's chunk key
    beat = link.ground.session
    assert beat is not None and len(link.responder) == 1  # the old session's keys are gone


class _Sessions:
    """A receiver over several sessions (a responder's routing, without its table)."""

    def __init__(self, *sessions: Sess) -> None:
        self.by_id = {s.session_id: s for s in sessions}

    def check(self, frame: bytes) -> None:
        self.by_id[frame[4:20]].check(frame)

    def open(self, frame: bytes) -> Open:
        return self.by_id[frame[4:20]].open(frame)


def _pair(sid: bytes) -> tuple[Sess, Sess]:
    """The two sides of a session with id ``sid`` (keys of its own)."""
    i2r, r2i = os.urandom(32), os.urandom(32)
    initiator = Sess(sid, Dir.I2R, "responder", i2r, r2i, signing_key=GCS_KEY)
    responder = Sess(sid, Dir.R2I, "gcs", r2i, i2r, peer_verify_key=GCS_KEY.public_key())
    return initiator, responder


def test_a_shared_handle_never_lets_one_session_refuse_the_others_frames() -> None:
    old_i, old_r = _pair(b"\0" * 7 + b"\1" + b"o" * 7 + b"\x42")
    new_i, new_r = _pair(b"\0" * 7 + b"\2" + b"n" * 7 + b"\x42")  # the same handle, 0x42
    receiver = _Sessions(old_r, new_r)
    sessions = [old_r, new_r]
    for _ in range(3):  # the old session's counters run ahead
        for purpose in Purpose:
            old_r.open(old_i.seal(b"x" * 8, purpose))
    for purpose in Purpose:  # the new session's first frames: counter 0, used in the old
        opened = open_compact(compact(new_i.seal(b"y" * 8, purpose)), sessions, Dir.I2R, receiver)
        assert (opened.session_id, opened.counter) == (new_r.session_id, 0)
    replay = compact(old_i.seal(b"z" * 8))
    open_compact(replay, sessions, Dir.I2R, receiver)
    with pytest.raises(CounterReplayedError):  # the old session's replay names itself
        open_compact(replay, sessions, Dir.I2R, receiver)
    forged = bytearray(compact(old_i.seal(b"w" * 8)))  # counter 4: fresh in both windows
    forged[-1] ^= 1
    with pytest.raises(SignatureInvalidError):
        open_compact(bytes(forged), sessions, Dir.I2R, receiver)


def test_replayed_chunks_of_opened_commands_cannot_crowd_out_a_new_one(link: EndPair) -> None:
    old = []
    for n in range(6):  # the attacker records six commands, all delivered
        frames = link.ground.from_local(arm(param1=float(n)))
        old.append(frames)
        link.up(frames)
    for t in range(4):  # and replays 19 of 20 chunks of four: none is buffered
        link.up(old[t][:19])
    assert link.refused == ["REPLAY_DETECTED"] * 76
    fresh = link.ground.from_local(arm(param1=9.0))
    for i, chunk in enumerate(fresh):
        link.up([chunk, old[4 + i % 2][0]])
    assert [c.param1 for c in link.commands()][-1] == 9.0
    assert link.vehicle.reassembly.evicted == 0


def test_a_silent_vehicle_end_gets_a_handshake_without_its_hint(
    link: EndPair, clock: ManualClock
) -> None:
    link.responder = Responder(ROBOT_KEM, {"gcs": GCS_KEY.public_key()}, clock=clock)
    link.vehicle = VehicleEnd(link.responder, clock=clock)  # restarted; its hints stolen
    beat = plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4))
    for _ in range(6):  # the GCS heartbeat each second; nothing authenticated comes back
        clock.advance(1)
        link.up(link.ground.from_local(beat))
    assert link.refused.count("UNKNOWN_SESSION") == 5  # the sixth carried a new HS1 too
    link.up(link.ground.from_local(arm()))
    assert len(link.commands()) == 1


def test_the_link_counts_plain_mavlink_quietly_and_exports_the_ends_drops(
    clock: ManualClock,
) -> None:
    refusals: list[FrameRefusal] = []
    made = EndPair(clock)
    local, air = FakeTransport("udpin:0.0.0.0:1", fixed=False), FakeTransport("udpout:1.2.3.4:5")
    pq = PqLink(made.ground, local, air, on_reject=refusals.append)
    pq.start()  # the first HS1 goes out, and is lost
    for n in range(9):
        local.inject(arm(param1=float(n)), ("10.0.0.1", 9))
    clock.advance(6)
    air.inject(plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4), sysid=1))  # MAVProxy's own
    air.inject(raw_chunk((7, 0, 1, 1, 3), b"x"))
    local.inject(arm(), ("10.0.0.1", 9))
    assert pq.dropped == {
        "air:PLAIN": 1,
        "air:UNKNOWN_SESSION": 1,
        "local:QUEUE_FULL": 1,
        "local:QUEUE_EXPIRED": 8,
    }
    assert [r.code for r in refusals] == ["UNKNOWN_SESSION"]


def test_a_chunk_planted_ahead_cannot_spoil_the_next_handshake(
    clock: ManualClock, monkeypatch: pytest.MonkeyPatch
) -> None:
    link = EndPair(clock)
    planted = link.ground.sender.transfer + 1  # the next transfer number, were it counted
    # The handshake's number is random; pinned here to one the attacker did not guess.
    monkeypatch.setattr(secrets, "randbelow", lambda n: (planted + 1) % n)
    link.up([raw_chunk((planted, 0, 32, 1, ChunkKind.HS1), b"x")])
    link.up(link.ground.handshake())
    assert link.ground.session is not None


class Wire(FakeTransport):
    """A fake air transport whose writes reach another link's air side (when connected)."""

    def __init__(self, text: str) -> None:
        super().__init__(text)
        self.peer: Wire | None = None

    def _write(self, data: bytes, peer: object) -> None:
        super()._write(data, peer)
        if self.peer is not None:
            self.peer.inject(bytes(data))


def _ends(clock: ManualClock) -> tuple[PqLink, PqLink, Wire, Wire, list[SessionEvent]]:
    """A ground and a vehicle link whose timers never fire on their own (the test ticks)."""
    made, events = EndPair(clock, air_bps=FAST_AIR_BPS), list[SessionEvent]()
    ground_air, vehicle_air = Wire("udpout:1.2.3.4:5"), Wire("udpout:1.2.3.4:6")
    ground = PqLink(
        made.ground, FakeTransport("udpin:0.0.0.0:1", fixed=False), ground_air,
        on_session=events.append, tick_s=3600,
    )  # fmt: skip
    vehicle = PqLink(
        made.vehicle, FakeTransport("udpout:1.2.3.4:7"), vehicle_air,
        on_session=events.append, tick_s=3600,
    )  # fmt: skip
    vehicle.start()
    return ground, vehicle, ground_air, vehicle_air, events


def test_the_timer_thread_retries_without_being_asked(clock: ManualClock) -> None:
    made = EndPair(clock, air_bps=FAST_AIR_BPS)
    air = FakeTransport("udpout:1.2.3.4:5")
    ground = PqLink(made.ground, FakeTransport("udpin:0.0.0.0:1", fixed=False), air, tick_s=0.01)
    ground.start()
    first = len(air.sent)
    clock.advance(2)
    until("a second handshake from the timer", lambda: len(air.sent) == 2 * first)
    ground.stop()


def test_each_session_change_is_reported_once_and_counted(clock: ManualClock) -> None:
    ground, vehicle, ground_air, vehicle_air, events = _ends(clock)
    ground_air.peer, vehicle_air.peer = vehicle_air, ground_air
    ground.start()
    beat = plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4), sysid=1)
    for _ in range(3):  # telemetry and ticks change nothing while the session is live
        vehicle.local.inject(beat)  # type: ignore[attr-defined]
        ground.tick()
        vehicle.tick()
    assert sorted((e.end, e.kind) for e in events) == [
        ("ground", "established"),
        ("vehicle", "established"),
    ]
    clock.advance(5)  # nothing authenticated either way: both notice, once
    vehicle.tick()
    vehicle.tick()
    vehicle_air.peer = None  # the downlink fails: the ground end's new handshake is unanswered
    ground.tick()
    ground.tick()
    assert sorted((e.end, e.kind) for e in events[2:]) == [
        ("ground", "lost"),
        ("vehicle", "established"),  # that handshake's session, which the ground never gets
        ("vehicle", "lost"),
    ]
    vehicle_air.peer = ground_air
    clock.advance(2)
    ground.tick()  # a new handshake, answered
    assert sorted((e.end, e.kind) for e in events[5:]) == [
        ("ground", "established"), ("vehicle", "rekeyed"),
    ]  # fmt: skip
    assert isinstance(ground.end, GroundEnd) and ground.end.session is not None
    ground.end.session._send[Purpose.DATA] = NonceCounter(REKEY_AFTER)
    gcs_beat = plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4))
    ground.local.inject(gcs_beat, ("10.0.0.1", 9))  # type: ignore[attr-defined]
    assert sorted((e.end, e.kind) for e in events[7:]) == [
        ("ground", "rekeyed"), ("vehicle", "rekeyed"),
    ]  # fmt: skip
    counts = ground.counts()
    assert counts.up and counts.sessions == {"established": 2, "lost": 1, "rekeyed": 1}
    assert counts.handshakes == {"started": 4, "completed": 3, "failed": 1}
    assert counts.chunks["sent"] == len(ground_air.sent)
    assert counts.chunks["received"] == counts.chunks["reassembled"] == 3 + 3  # HS2s, beats
    ground.stop()
    vehicle.stop()


def test_telemetry_without_a_session_is_counted_not_refused(clock: ManualClock) -> None:
    refusals: list[FrameRefusal] = []
    made = EndPair(clock)
    fc = FakeTransport("udpout:1.2.3.4:7")
    vehicle = PqLink(
        made.vehicle, fc, FakeTransport("udpin:0.0.0.0:1", fixed=False),
        on_reject=refusals.append, tick_s=3600,
    )  # fmt: skip
    vehicle.start()
    for _ in range(84):
        fc.inject(plain(lambda m: m.heartbeat_send(2, 3, 0, 0, 4), sysid=1))
    assert refusals == []
    counts = vehicle.counts()
    assert counts.dropped == {"local:NO_SESSION": 84} and counts.refused == {}
    vehicle.stop()


def test_the_ground_end_retries_a_lost_handshake_on_its_timer(clock: ManualClock) -> None:
    """No local traffic at all: the timer alone hand-shakes again, every retry_s, until
    a session answers, and then stops."""
    ground, vehicle, ground_air, vehicle_air, events = _ends(clock)
    ground.start()  # the vehicle's air is not connected yet: this HS1 is lost
    first = len(ground_air.sent)
    ground.tick()
    assert len(ground_air.sent) == first  # not before retry_s
    ground_air.peer, vehicle_air.peer = vehicle_air, ground_air
    clock.advance(2)
    ground.tick()
    assert len(ground_air.sent) == 2 * first
    ground_session = ground.end.live
    assert ground_session is not None
    assert sorted(map(str, events)) == [
        f"pq ground: session established ({ground_session.session_id.hex()}, peer responder)",
        f"pq vehicle: session established ({ground_session.session_id.hex()}, peer gcs)",
    ]
    clock.advance(2)
    ground.tick()
    assert len(ground_air.sent) == 2 * first  # a session: no more handshakes
    assert ground.counts().handshakes == {"started": 2, "completed": 1, "failed": 1}
    ground.stop()
    vehicle.stop()
