"""The PQ vehicle end (the responder): handshakes it accepts or refuses, what it requires signed."""

from __future__ import annotations

import os
import random
from collections.abc import Callable

import pytest

from antireplay import ManualClock
from antireplay.core.errors import (
    MessageStaleError,
    SignatureInvalidError,
    UnknownSenderError,
    UnknownSessionError,
)
from antireplay.mavlink.codec import parse_frame
from antireplay.mavlink.pq import (
    CHUNK_DATA,
    ChunkKind,
    ChunkSender,
    GroundEnd,
    VehicleEnd,
)
from antireplay.mavlink.pq.repair import Op, repair_frame
from antireplay.mavlink.pq.wire import HANDSHAKE_SHARE, parse_refusal
from antireplay.pq.session import Initiator, Responder

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as dialect

from harness.pq_ends import (
    GCS_KEY,
    ROBOT_KEM,
    STRANGER_KEY,
    EndPair,
    arm,
    blob,
    connected,
    plain,
    raw_chunk,
)


def test_handshake_replay_never_opens_a_session(clock: ManualClock) -> None:
    link = EndPair(clock)
    hs1 = link.ground.handshake()
    link.up(hs1)
    assert len(link.responder) == 1
    link.up(hs1)
    assert link.refused == ["REPLAY_DETECTED"] and len(link.responder) == 1
    clock.advance(40)
    link.up(hs1)
    # stale: refused, and answered with a PQ_REFUSAL the ground end (no handshake pending)
    # refuses in turn as another attempt's
    assert link.refused[-2:] == ["MESSAGE_STALE", "REPLAY_DETECTED"]
    assert len(link.responder) == 1
    with pytest.raises(MessageStaleError):  # the reassembled blob is the HS1 itself
        link.responder.accept_handshake(blob(hs1))
    # a replayed HS2 at the ground end finishes nothing: no handshake is pending
    session = link.ground.session
    hs2 = ChunkSender(1, 197).frames(b"\xa2" + bytes(81), ChunkKind.HS2)
    link.down(hs2)
    assert link.refused[-1] == "UNKNOWN_SESSION" and link.ground.session is session


def test_handshake_flood_keeps_the_almost_complete_handshake(clock: ManualClock) -> None:
    link = EndPair(clock)
    hs1 = link.ground.handshake()
    assert len(hs1) == 29  # 26 chunks and 3 parity
    link.up([raw for i, raw in enumerate(hs1) if i not in (0, 3, 28)])  # two of one group
    rng = random.Random(5)
    for transfer in range(200):  # first chunks of made-up handshakes from other systems
        fields = (transfer, 0, 26, CHUNK_DATA, ChunkKind.HS1)
        link.up([raw_chunk(fields, rng.randbytes(CHUNK_DATA), sysid=rng.randrange(256))])
    link.up(hs1[:1])
    assert link.ground.session is not None
    assert link.vehicle.reassembly.evicted == 199


def test_the_vehicle_end_draws_session_ids_whose_handles_differ(clock: ManualClock) -> None:
    link = EndPair(clock, max_sessions=8)
    for _ in range(8):  # eight live sessions, none carrying a frame (none superseded)
        link.connect()
    assert len({s.session_id[-1] for s in link.vehicle._sessions}) == 8
    avoid = lambda sid: sid[-1] < 0x80  # noqa: E731 - half the handles taken: 2**-64 to miss
    handles = []
    for _ in range(8):  # without the redraw, all eight in the free half by chance: 1 in 256
        hs1 = link.ground.initiator.start(ROBOT_KEM.public_key())
        handles.append(link.responder.accept_handshake(hs1, avoid)[1][2 + 15])
    assert min(handles) >= 0x80, handles


def test_a_message_that_must_be_signed_is_refused_in_a_data_frame(clock: ManualClock) -> None:
    link = EndPair(clock)
    link.ground = GroundEnd(
        Initiator("gcs", GCS_KEY, clock), ROBOT_KEM.public_key(), clock=clock, signed=frozenset()
    )
    link.connect()
    (frame,) = link.ground.from_local(arm())  # an HMAC data frame
    link.up([frame])
    assert not link.commands() and link.refused == ["SIGNATURE_REQUIRED"]


@pytest.mark.parametrize(
    "build",
    [
        lambda m: m.mission_item_send(1, 1, 0, 0, 16, 0, 1, 0, 0, 0, 0, 1.0, 2.0, 30.0),
        lambda m: m.mission_write_partial_list_send(1, 1, 0, 3),
        lambda m: m.param_ext_set_send(1, 1, b"ARMING_CHECK", b"0", 6),
        lambda m: m.serial_control_send(10, 0, 0, 0, 4, [ord(c) for c in "rebo"] + [0] * 66),
        lambda m: m.file_transfer_protocol_send(0, 1, 1, [0] * 251),
        lambda m: m.set_position_target_local_ned_send(0, 1, 1, 1, 0, 1, 2, 3, *[0] * 8),
        lambda m: m.set_position_target_global_int_send(0, 1, 1, 5, 0, 1, 2, 3, *[0] * 8),
    ],
)
def test_command_carrying_messages_are_signed_by_default(
    clock: ManualClock, build: Callable[[dialect.MAVLink], None]
) -> None:
    link = connected(clock)
    frames = link.ground.from_local(plain(build))
    assert len(frames) > 1  # an ML-DSA-87 signature: several chunks
    link.up(frames)
    assert len(link.delivered) == 1 and link.refused == []


def test_vehicle_end_restart_the_ground_end_handshakes_again(clock: ManualClock) -> None:
    link = connected(clock)
    link.down(link.vehicle.from_local(plain(lambda m: m.heartbeat_send(2, 3, 0, 0, 4), sysid=1)))
    link.responder = Responder(ROBOT_KEM, {"gcs": GCS_KEY.public_key()}, clock=clock)
    link.vehicle = VehicleEnd(link.responder, clock=clock)  # restarted: no session
    with pytest.raises(UnknownSessionError):
        link.vehicle.from_air(
            link.ground.from_local(plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4)))[0]
        )
    hint = link.vehicle.hint()
    assert link.vehicle.hint() == []  # rate-limited
    clock.advance(3)  # the ground end heard nothing authenticated for retry_s
    link.down(hint)
    link.up(link.ground.from_local(arm()))
    assert len(link.commands()) == 1


def _stranger_hs1s(clock: ManualClock, count: int) -> list[list[bytes]]:
    """``count`` HS1s signed with a key the vehicle end does not know, chunked."""
    initiator = Initiator("gcs", STRANGER_KEY, clock)
    sender = ChunkSender(255, 197)
    return [
        sender.frames(initiator.start(ROBOT_KEM.public_key()), ChunkKind.HS1, transfer=n)
        for n in range(count)
    ]


def _refusals(vehicle: VehicleEnd, frames: list[bytes]) -> list[bytes]:
    """Feed ``frames``; the ``PQ_REFUSAL`` s the vehicle end answers with (as the link
    collects them after the error)."""
    out: list[bytes] = []
    for raw in frames:
        try:
            vehicle.from_air(raw)
        except (SignatureInvalidError, UnknownSenderError):
            out += vehicle.answered()
    return out


def test_a_refused_hs1_is_answered_once_under_its_own_key(clock: ManualClock) -> None:
    """The same HS1 again (another transfer number, as a POKE's repair or an attacker
    could send it) gets no second refusal: one per attempt."""
    link = EndPair(clock)
    (frames,) = _stranger_hs1s(clock, 1)
    (refusal,) = _refusals(link.vehicle, frames)
    again = ChunkSender(255, 197).frames(blob(frames), ChunkKind.HS1, transfer=999)
    assert _refusals(link.vehicle, again) == []
    assert link.vehicle.refusals == {"sent": 1, "withheld": 1}
    parsed = parse_refusal(parse_frame(refusal))
    key = link.responder.refusal_key(blob(frames))
    assert key is not None and parsed.verify(blob(frames), key)
    assert parsed.target == (255, 197) and parsed.transfer == 0 and parsed.code == 1


def test_a_flood_of_bad_handshakes_gets_refusals_only_within_the_airtime_budget(
    clock: ManualClock,
) -> None:
    """No amplifier: 40 distinct refused HS1s at once get two refusals (the burst), and
    then HS1s ten a second, faster than refusals refill, get them at the known identity's
    part of the budget (half of 5 % of 57,600 baud, one peer: 144 bytes a second)."""
    link = EndPair(clock)
    hs1s = _stranger_hs1s(clock, 140)
    first = _refusals(link.vehicle, [raw for frames in hs1s[:40] for raw in frames])
    assert len(first) == 2 and link.vehicle.refusals["withheld"] == 38
    later: list[bytes] = []
    for frames in hs1s[40:]:  # 10 s
        clock.advance(0.1)
        later += _refusals(link.vehicle, frames)
    allowed = HANDSHAKE_SHARE * 5_760 / 2 * 10
    assert allowed - 2 * 107 <= sum(map(len, later)) <= allowed, len(later)


def _unknown_hs1s(clock: ManualClock, count: int) -> list[list[bytes]]:
    """``count`` HS1s from an identity the vehicle end does not know (anybody's junk)."""
    initiator = Initiator("mallory", STRANGER_KEY, clock)
    sender = ChunkSender(7, 7)
    return [
        sender.frames(initiator.start(ROBOT_KEM.public_key()), ChunkKind.HS1, transfer=n)
        for n in range(count)
    ]


def test_junk_claiming_unknown_names_cannot_starve_a_known_identitys_refusal(
    clock: ManualClock,
) -> None:
    """Review 3: junk HS1s (an unknown identity) spend their own part of the refusal
    budget; the misconfigured ground end's HS1 right after them is still refused aloud."""
    link = EndPair(clock)
    junk = _refusals(link.vehicle, [raw for frames in _unknown_hs1s(clock, 4) for raw in frames])
    assert len(junk) == 2 and link.vehicle.refusals["withheld"] == 2
    (frames,) = _stranger_hs1s(clock, 1)
    assert len(_refusals(link.vehicle, frames)) == 1


def test_a_withheld_refusal_is_sent_when_its_hs1_is_poked_again(clock: ManualClock) -> None:
    """Review 3: an HS1 whose refusal the budget withheld is not recorded as answered:
    its POKE (or the HS1 again), once the budget allows, gets the refusal."""
    link = EndPair(clock)
    drained, (frames,) = _stranger_hs1s(clock, 2), _stranger_hs1s(clock, 1)
    frames = ChunkSender(255, 197).frames(blob(frames), ChunkKind.HS1, transfer=77)
    assert len(_refusals(link.vehicle, [raw for f in drained for raw in f])) == 2
    assert _refusals(link.vehicle, frames) == []  # withheld: the budget is spent
    poke = repair_frame(Op.POKE, 77, (0, 0), 0, None, sysid=255, compid=197)
    assert link.vehicle.from_air(poke).air == []  # still spent: no refusal, no NACK
    clock.advance(1.0)
    (refusal,) = link.vehicle.from_air(poke).air
    parsed = parse_refusal(parse_frame(refusal))
    key = link.responder.refusal_key(blob(frames))
    assert key is not None and parsed.verify(blob(frames), key) and parsed.transfer == 77
    clock.advance(10.0)
    assert link.vehicle.from_air(poke).air == []  # answered: once per HS1


def test_a_poke_for_a_refused_hs1_gets_no_nack(clock: ManualClock) -> None:
    """Its refusal lost, the ground end pokes: the vehicle end does not ask for the whole
    HS1 again (it would be refused again), so a lost refusal costs no repair traffic."""
    link = EndPair(clock)
    (frames,) = _stranger_hs1s(clock, 1)
    assert len(_refusals(link.vehicle, frames)) == 1
    poke = repair_frame(Op.POKE, 0, (0, 0), 0, None, sysid=255, compid=197)
    assert link.vehicle.from_air(poke).air == []
    assert link.vehicle.repairs["nack_sent"] == 0
    unknown = repair_frame(Op.POKE, 1, (0, 0), 0, None, sysid=255, compid=197)
    assert link.vehicle.from_air(unknown).air  # a transfer never seen: NACKed whole


@pytest.mark.parametrize("air_bps", [0, -7_200])
def test_the_vehicle_end_refuses_an_air_rate_that_is_not_positive(
    clock: ManualClock, air_bps: int
) -> None:
    """Review 8: a zero or negative rate would make the refusal budget unbounded."""
    responder = Responder(ROBOT_KEM, {"gcs": GCS_KEY.public_key()}, clock=clock)
    with pytest.raises(ValueError, match="air_bps must be positive"):
        VehicleEnd(responder, air_bps=air_bps, clock=clock)
