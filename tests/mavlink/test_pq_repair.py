"""Loss-tolerant transfers: parity and repair requests on a seeded lossy radio (simulated
time), GCS retries answered from what the ends hold, and repair requests an attacker
forges or replays changing nothing."""

from __future__ import annotations

import os
from typing import Any

import pytest
from cryptography.hazmat.primitives.asymmetric import mldsa, mlkem
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay import ManualClock
from antireplay.core.errors import SignatureInvalidError
from antireplay.mavlink.codec import parse_frame
from antireplay.mavlink.pq import (
    CHUNK_DATA,
    MAX_CHUNKS,
    ChunkKind,
    ChunkSender,
    GroundEnd,
    Reassembler,
    VehicleEnd,
    parse_chunk,
)
from antireplay.mavlink.pq.link import Pacer, PqLink
from antireplay.mavlink.pq.repair import (
    EVERYTHING,
    RESEND_BUDGET,
    Op,
    bind_ack,
    parse_repair,
    repair_frame,
    repair_key,
    unbind_ack,
)
from antireplay.mavlink.pq.wire import LINE_BITS, MAX_PARITY, MSG_REPAIR, inner_of
from antireplay.pq.session import Initiator, Responder
from harness.lossy_air import Radio, build
from harness.mavlink_frames import FakeTransport
from harness.pq_ends import FAST_AIR_BPS

GCS_KEY = mldsa.MLDSA87PrivateKey.generate()
ROBOT_KEM = mlkem.MLKEM1024PrivateKey.generate()
TODAY_AIR_BYTES = 5_327  # per delivered command at 0 % loss, before parity and repairs


def radio(loss: float, bps: int | None, seed: int, budget_bps: int | None = None) -> Radio:
    """Both ends over a lossy radio of ``bps``; the ground end's handshake budget is that of
    ``budget_bps`` when given (a test of repairs, not of airtime)."""
    clock = ManualClock()
    ground = GroundEnd(
        Initiator("gcs", GCS_KEY, clock), ROBOT_KEM.public_key(), clock=clock,
        air_bps=budget_bps or bps,
    )  # fmt: skip
    responder = Responder(ROBOT_KEM, {"gcs": GCS_KEY.public_key()}, clock=clock)
    vehicle = VehicleEnd(responder, clock=clock, air_bps=bps)
    return Radio(ground, vehicle, clock, loss, bps, seed)


def commands(made: Radio, n: int = 100) -> tuple[list[float], float]:
    """Times to ACK of the delivered ones, and air bytes per delivered command."""
    before = made.up.sent + made.down.sent
    times = [t for i in range(n) if (t := made.command(float(i))) is not None]
    return sorted(times), (made.up.sent + made.down.sent - before) / max(1, len(times))


@pytest.mark.parametrize("bps", [None, 57_600])
@pytest.mark.parametrize(("loss", "least"), [(0.05, 99), (0.10, 95)])
def test_lossy_radio_delivers_commands_each_once(loss: float, least: int, bps: int | None) -> None:
    made = radio(loss, bps, seed=7)
    assert made.start() < 5.0
    times, _ = commands(made)
    assert len(times) >= least
    assert set(made.delivered.values()) == {1}  # never twice, retries and repairs included
    if loss == 0.05:
        assert times[89] <= 1.5  # p90 to ACK, within the GCS's first try
    assert made.ground.repairs["resent"] > 0 and made.vehicle.repairs["nack_sent"] > 0


def test_no_loss_costs_parity_only() -> None:
    made = radio(0.0, 57_600, seed=1)
    made.start()
    times, air = commands(made, 20)
    assert len(times) == 20 and air <= 1.3 * TODAY_AIR_BYTES
    assert made.vehicle.repairs == {}  # no NACK, no POKE: parity only
    assert set(made.ground.repairs) == {"ack_duplicate"}  # each ACK's second copy, dropped
    assert made.ground.airtime["parity"] > 0 and made.ground.airtime["cmd"] > 0


def test_a_session_comes_up_within_5s_at_10_percent_loss() -> None:
    """Repairs, not retries, bring it up (the handshake budget aside: one HS1's allowance
    leaves repairs of the first one at 5 % of the line, :mod:`.ground`)."""
    for seed in range(10):
        assert radio(0.10, 57_600, seed, budget_bps=FAST_AIR_BPS).start() < 5.0, seed


class Signs:
    """A signing key that counts its signatures."""

    def __init__(self, key: mldsa.MLDSA87PrivateKey) -> None:
        self.key, self.calls = key, 0

    def sign(self, data: bytes, context: bytes) -> bytes:
        self.calls += 1
        return self.key.sign(data, context)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.key, name)


def test_a_gcs_retry_is_no_new_transfer_and_the_ack_is_answered_again() -> None:
    made = radio(0.0, None, seed=1)
    made.start()
    assert made.ground.session is not None
    signs = Signs(GCS_KEY)
    made.ground.session.signing_key = signs  # type: ignore[assignment]
    arm = build(lambda m: m.command_long_send(1, 1, 400, 0, 1.0, 0, 0, 0, 0, 0, 0), 255)
    made.down.loss = 1.0  # the downlink fails: the ACK is lost
    made.send(made.up, made.ground.handle_local(arm).air, made.to_vehicle)
    made.run_until(made.clock.monotonic() + 1.5)
    assert made.delivered == {1.0: 1} and not made._acked
    made.down.loss = 0.0
    retry = made.ground.handle_local(arm)  # the GCS's second try: a POKE, 35 bytes
    assert len(retry.air) == 1 and len(retry.air[0]) < 40 and retry.local == []
    made.send(made.up, retry.air, made.to_vehicle)
    made.run_until(made.clock.monotonic() + 0.5)
    assert made._acked and made.vehicle.repairs["answered"] == 1
    third = made.ground.handle_local(arm)  # a third try: the ACK the ground end saw
    assert third.air == [] and len(third.local) == 1
    assert signs.calls == 1 and made.delivered == {1.0: 1}
    assert made.ground.retries == {"poked": 1, "answered": 1}
    made.run_until(made.clock.monotonic() + 5)  # after the retry window: a new command
    assert len(made.ground.handle_local(arm).air) == 22 and signs.calls == 2


def test_the_retry_window_is_fixed_from_the_first_try() -> None:
    """A command repeated every 1.9 s is answered within ``retry_window_s`` (6 s) of its
    first try and executed again after it: repeats never hold the window open."""
    made = radio(0.0, None, seed=1)
    made.start()
    arm = _command(400, 1.0)
    for _ in range(5):
        made.send(made.up, made.ground.handle_local(arm).air, made.to_vehicle)
        made.run_until(made.clock.monotonic() + 1.9)
    assert made.delivered == {1.0: 2}  # at 0 s and at 7.6 s
    assert made.ground.retries == {"answered": 3}


def test_forged_and_replayed_repair_requests_change_nothing() -> None:
    made = radio(0.0, None, seed=1)
    made.start()
    ground, vehicle = made.ground, made.vehicle
    session = ground.session
    assert session is not None
    frames = ground.from_local(build(lambda m: m.command_long_send(1, 1, 400, 0, 1, *[0] * 6), 255))
    transfer = ground.sender.transfer
    vehicle_ids = {"sysid": vehicle.sender.sysid, "compid": vehicle.sender.compid}
    target = (ground.sender.sysid, ground.sender.compid)
    forged = repair_frame(Op.NACK, transfer, target, EVERYTHING, os.urandom(32), **vehicle_ids)
    with pytest.raises(SignatureInvalidError):
        ground.from_air(forged)
    unsigned = repair_frame(Op.NACK, transfer, target, EVERYTHING, None, **vehicle_ids)
    assert ground.from_air(unsigned).air == []  # no session transfer for an unsigned NACK
    genuine = repair_frame(
        Op.NACK, transfer, target, EVERYTHING, repair_key(session.recv_key), **vehicle_ids
    )
    resent = [f for _ in range(5) for f in ground.from_air(genuine).air]  # replayed 5 times
    assert len(resent) == RESEND_BUDGET * len(frames)  # bounded
    assert set(resent) == set(frames)  # the same authenticated bytes, nothing new
    for raw in frames + resent:
        made.to_vehicle(raw)
    assert made.delivered == {1.0: 1}  # once; the rest de-duplicated or refused as replays
    assert made.refused["vehicle:REPLAY_DETECTED"] == 2 * len(frames)
    poke = repair_frame(Op.POKE, transfer, (0, 0), 0, os.urandom(32), sysid=255, compid=197)
    with pytest.raises(SignatureInvalidError):
        vehicle.from_air(poke)
    sessions, current = len(vehicle.responder), vehicle.current
    for n in range(10):  # unauthenticated POKEs: rate-limited NACKs, nothing else
        vehicle.from_air(repair_frame(Op.POKE, n, (0, 0), 0, None, sysid=9, compid=9))
    assert len(vehicle.responder) == sessions and vehicle.current is current
    assert vehicle.repairs["nack_sent"] <= 2


def test_reassembly_memory_stays_bounded_under_a_flood_with_parity() -> None:
    reassembler = Reassembler(clock=ManualClock())
    for sysid in range(200):  # handshakes with parity from many senders, never complete
        frames = ChunkSender(sysid, 9).frames(os.urandom(31 * CHUNK_DATA), ChunkKind.HS1)
        for raw in frames[2:]:  # two of a group lost: never complete
            reassembler.feed(parse_chunk(parse_frame(raw)))
    assert reassembler.buffered <= 2 * (MAX_CHUNKS + MAX_PARITY) * CHUNK_DATA


def test_the_pacer_keeps_to_the_radio_rate_and_lets_telemetry_through_first() -> None:
    clock = ManualClock()
    pacer = Pacer(57_600, clock)  # 5,587 bytes a second (97 % of 5,760), 559 of burst
    made = radio(0.0, None, seed=1)
    made.start()
    command = made.ground.from_local(
        build(lambda m: m.command_long_send(1, 1, 400, 0, 1, *[0] * 6), 255)
    )
    beat = made.ground.from_local(build(lambda m: m.heartbeat_send(6, 8, 0, 0, 4), 255))
    pacer.push(command, None)
    first, wait_s = pacer.pop()
    assert sum(len(f) for f, _ in first) <= 559 and wait_s > 0
    pacer.push(beat, None)  # telemetry arrives while the command waits for the air
    clock.advance(wait_s)
    after, _ = pacer.pop()
    assert after[0][0] == beat[0]  # ahead of the command's remaining chunks
    sent = sum(len(f) for f, _ in first + after)
    began = clock.monotonic() - wait_s
    while pacer.bulk:
        clock.advance(0.05)
        ready, _ = pacer.pop()
        sent += sum(len(f) for f, _ in ready)
    assert sent == sum(map(len, command + beat))
    assert sent <= 559 + 5_587 * (clock.monotonic() - began)  # never faster than the radio
    for _ in range(200):  # telemetry beyond two seconds of queue is dropped, and counted
        pacer.push(beat, None)
    assert pacer.paced_out > 0 and pacer.queued <= 2 * 5_587 + len(beat[0])
    slow = Pacer(1_200, clock, bulk_ttl_s=120)  # 116 bytes a second: still two full chunks of burst
    slow.push(command[:3], None)
    clock.advance(60)
    assert len(slow.pop()[0]) == 2


def test_a_handshake_repair_is_answered_to_its_sender_never_learned() -> None:
    """A vehicle end on ``udpin`` knows no ground peer before a handshake opens: the NACK
    for an incomplete HS1, at once or on its timer (the HS1's tail lost), goes back to
    the address its chunks came from, and that address is not learned."""
    made = radio(0.0, None, seed=1, budget_bps=FAST_AIR_BPS)
    air = FakeTransport("udpin:0.0.0.0:1", fixed=False)
    fc = FakeTransport("udpout:1.2.3.4:7")
    link = PqLink(made.vehicle, fc, air, tick_s=3600)
    link.start()
    ground_at = ("10.0.0.9", 14550)
    for lost in [(0, 3), (0, 3, 28)]:  # two of one group; then the last chunk too
        hs1 = made.ground.handshake()
        for raw in [r for i, r in enumerate(hs1) if i not in lost]:
            air.inject(raw, ground_at)
        if 28 in lost:
            assert air.sent[1:] == []  # nothing tells it the HS1 ended: its timer will
            made.clock.advance(made.vehicle.gap_s)
            link.tick()
        nack, to = air.sent[-1]
        assert (
            to == ground_at
            and parse_repair(parse_frame(nack)).transfer
            == parse_chunk(parse_frame(hs1[0])).transfer
        )
        made.clock.advance(0.001)  # the HS1 has left (by its budget's line rate)
        resent = made.ground.from_air(nack).air
        assert len(resent) == 1  # one of the two: parity rebuilds the other
    assert {to for _, to in air.sent} == {ground_at}
    sent = len(air.sent)
    fc.inject(build(lambda m: m.heartbeat_send(2, 3, 0, 0, 4), 1))  # telemetry: no peer yet
    assert len(air.sent) == sent and link.counts().dropped == {"local:NO_SESSION": 1}
    link.stop()


def test_telemetry_overtaking_a_command_on_the_air_spoils_nothing() -> None:
    """The pacer sends one-chunk frames ahead of a command's chunks: a heartbeat sealed
    after the command (a later transfer number) arrives first, and the command still
    opens; its replay is still refused."""
    made = radio(0.0, None, seed=1)
    made.start()
    arm = build(lambda m: m.command_long_send(1, 1, 400, 0, 1, *[0] * 6), 255)
    command = made.ground.from_local(arm)
    beat = made.ground.from_local(build(lambda m: m.heartbeat_send(6, 8, 0, 0, 4), 255))
    for raw in beat + command:
        made.to_vehicle(raw)
    assert made.delivered == {1.0: 1} and made.refused == {}
    for raw in command:
        made.to_vehicle(raw)
    assert made.refused == {"vehicle:REPLAY_DETECTED": len(command)}


def _command(command: int, param1: float) -> bytes:
    return build(lambda m: m.command_long_send(1, 1, command, 0, param1, 1900, 0, 0, 0, 0, 0), 255)


def _acks_at_gcs(made: Radio) -> list[tuple[int, int]]:
    """Tap what reaches the GCS: (command, result) of each COMMAND_ACK."""
    seen: list[tuple[int, int]] = []
    passed = made.to_gcs

    def gcs(frames: list[bytes]) -> None:
        for plain in frames:
            msg = dialect.MAVLink(None).decode(bytearray(plain))
            if msg.get_type() == "COMMAND_ACK":
                seen.append((msg.command, msg.result))
        passed(frames)

    made.to_gcs = gcs  # type: ignore[method-assign]
    return seen


def test_a_replayed_poke_never_acks_a_blocked_command() -> None:
    """ARM's ACK lost once, so the GCS retried and the ground end POKEd (recorded).  Later
    DISARM (same command number) is jammed and the POKE replayed: the vehicle end's ACK
    again is bound to ARM's transfer, so the GCS hears nothing and DISARM's retry goes to
    the vehicle, never answered locally with ARM's ACK."""
    made = radio(0.0, None, seed=1)
    made.start()
    pokes: list[bytes] = []
    passed = made.to_vehicle

    def tap(raw: bytes) -> None:
        if parse_frame(raw).msgid == MSG_REPAIR:
            pokes.append(raw)
        passed(raw)

    made.to_vehicle = tap  # type: ignore[method-assign]
    arm, disarm = _command(400, 1.0), _command(400, 0.0)
    made.down.loss = 1.0
    made.send(made.up, made.ground.handle_local(arm).air, made.to_vehicle)
    made.run_until(made.clock.monotonic() + 1.5)
    made.down.loss = 0.0
    made.send(made.up, made.ground.handle_local(arm).air, made.to_vehicle)
    made.run_until(made.clock.monotonic() + 0.5)
    assert made._acked and len(pokes) == 1
    made.clock.advance(10)
    seen = _acks_at_gcs(made)
    made.up.loss = 1.0
    made.send(made.up, made.ground.handle_local(disarm).air, made.to_vehicle)
    made.run_until(made.clock.monotonic() + 0.3)
    made.up.loss = 0.0
    passed(pokes[0])  # the replay
    made.run_until(made.clock.monotonic() + 0.5)
    assert seen == []  # ARM's ACK again, dropped: no ACCEPTED for a DISARM never delivered
    assert made.ground.repairs["ack_duplicate"] >= 1
    retry = made.ground.handle_local(disarm)
    assert retry.local == [] and retry.air  # asked of the vehicle, not answered here
    made.send(made.up, retry.air, made.to_vehicle)
    made.run_until(made.clock.monotonic() + 1.0)
    assert made.delivered == {1.0: 1, 0.0: 1} and seen == [(400, 0)]


def test_an_ack_answers_only_its_own_transfer_under_plain_loss() -> None:
    """DO_SET_SERVO 5 lost whole, then servo 6 delivered and ACKed: servo 6's ACK is bound
    to servo 6's transfer; the GCS retry of servo 5 POKEs, the vehicle end says it never
    arrived (and never can: a later transfer opened), and the ground end sends it anew."""
    made = radio(0.0, None, seed=1)
    made.start()
    seen = _acks_at_gcs(made)
    servo5, servo6 = _command(183, 5.0), _command(183, 6.0)
    answers: list[bytes] = []
    passed = made.to_ground

    def tap(raw: bytes) -> None:
        if parse_frame(raw).msgid == MSG_REPAIR:
            answers.append(raw)
        passed(raw)

    made.to_ground = tap  # type: ignore[method-assign]
    made.up.loss = 1.0
    made.send(made.up, made.ground.handle_local(servo5).air, made.to_vehicle)
    made.run_until(made.clock.monotonic() + 0.3)
    made.up.loss = 0.0
    made.send(made.up, made.ground.handle_local(servo6).air, made.to_vehicle)
    made.run_until(made.clock.monotonic() + 0.5)
    assert made.delivered == {6.0: 1} and seen == [(183, 0)]
    retry = made.ground.handle_local(servo5)
    assert retry.local == []  # never servo 6's ACK
    made.send(made.up, retry.air, made.to_vehicle)
    made.run_until(made.clock.monotonic() + 1.0)
    assert made.delivered == {6.0: 1, 5.0: 1} and seen == [(183, 0), (183, 0)]
    assert made.ground.repairs["undelivered"] == 1 and len(answers) == 1
    assert made.ground.from_air(answers[0]).air == []  # replayed: its nonce is spent
    assert made.ground.handle_local(servo5).local == [made.ground._last_ack]  # its own ACK


def test_a_bound_ack_round_trips() -> None:
    ack = build(lambda m: m.command_ack_send(400, 0, 0, 0, 0, 0), 1)
    inner = inner_of(parse_frame(ack))
    assert unbind_ack(bind_ack(inner, 0xBEEF)) == (inner, 0xBEEF)
    assert unbind_ack(inner) == (inner, None)


@pytest.mark.parametrize(("held_s", "delivered"), [(4.0, 1), (300.0, 0)])
def test_a_withheld_command_released_late_is_refused_as_stale(
    held_s: float, delivered: int
) -> None:
    """An attacker withholds every chunk of a command and releases them later: within
    ``max_age_s`` (10 s) it is delivered, five minutes on it is refused (MESSAGE_STALE,
    counted), though the session is still up and the chunks authentic."""
    made = radio(0.0, None, seed=1)
    made.start()
    held: list[bytes] = []
    passed = made.to_vehicle
    made.to_vehicle = lambda raw: held.append(raw) if len(raw) > 200 else passed(raw)  # type: ignore[method-assign]
    made.send(made.up, made.ground.handle_local(_command(400, 7.0)).air, made.to_vehicle)
    made.run_until(made.clock.monotonic() + held_s)
    assert made.delivered == {} and made.ground.session is not None
    made.to_vehicle = passed  # type: ignore[method-assign]
    for raw in held:
        made.to_vehicle(raw)
    assert sum(made.delivered.values()) == delivered
    assert made.refused["vehicle:MESSAGE_STALE"] == made.vehicle.drops["STALE"] == 1 - delivered


def test_a_rekey_heeds_only_nacks_maced_in_the_live_session() -> None:
    """While a session is live, a rekey's HS1 is resent only for a NACK MACed in it: an
    unsigned one (anybody's, some 25 bytes) costs the ground end no airtime, while the
    vehicle end's own NACK for the chunks it missed still repairs the HS1."""
    made = radio(0.0, None, seed=1, budget_bps=FAST_AIR_BPS)
    made.start()
    ground, vehicle = made.ground, made.vehicle
    hs1 = ground.handshake()  # a rekey, the session still live
    target = (ground.sender.sysid, ground.sender.compid)
    forged = repair_frame(
        Op.NACK, ground._hs_transfer, target, EVERYTHING, None, sysid=1, compid=197
    )
    assert ground.from_air(forged).air == [] and ground.repairs["ignored"] == 1
    for raw in hs1[: len(hs1) - MAX_PARITY - 2]:  # its tail lost
        assert vehicle.from_air(raw).air == []
    made.clock.advance(1.0)
    nacks = vehicle.tick()
    assert nacks and parse_repair(parse_frame(nacks[0])).signed
    assert ground.from_air(nacks[0]).air  # the vehicle end's own NACK: repaired


def test_the_pacer_gives_long_transfers_their_share_and_drops_stale_ones() -> None:
    """An RC override at 110 % of a 57,600-baud line: a command still leaves within about
    twice its own airtime (a byte for each byte of one-chunk frames), and chunks queued
    longer than ``bulk_ttl_s`` (the GCS gave up) are dropped, counted, never sent late."""
    made = radio(0.0, None, seed=1)
    made.start()
    clock = made.clock
    pacer = Pacer(57_600, clock)
    rc = made.ground.from_local(
        build(lambda m: m.rc_channels_override_send(1, 1, *[1500] * 8), 255)
    )[0]
    step = len(rc) / (1.1 * 5_760)
    commands = [made.ground.from_local(_command(183, float(i))) for i in range(8)]
    born = {raw: clock.monotonic() for command in commands for raw in command}
    for command in commands:
        pacer.push(command, None)
    left: dict[bytes, float] = {}
    for _ in range(int(12 / step)):
        pacer.push([rc], None)
        left.update((raw, clock.monotonic()) for raw, _ in pacer.pop()[0] if raw in born)
        clock.advance(step)
    assert set(commands[0]) <= set(left)
    assert max(left[raw] for raw in commands[0]) - born[commands[0][0]] < 2.5
    assert max(left[raw] - born[raw] for raw in left) <= pacer.bulk_ttl_s  # nothing late
    assert pacer.paced_stale == sum(map(len, commands)) - len(left) > 0


def test_a_udpin_vehicle_peer_is_steered_by_nothing_unauthenticated() -> None:
    """Before a session, an unsigned POKE from elsewhere does not redirect the handshake's
    NACK; in a session, a relayed copy of a command's last chunk, arriving first from
    the attacker's address, does not become the air peer: the first authentic frame's does."""
    made = radio(0.0, None, seed=1)
    ground, clock = made.ground, made.clock
    air = FakeTransport("udpin:0.0.0.0:1", fixed=False)
    link = PqLink(made.vehicle, FakeTransport("udpout:1.2.3.4:7"), air, tick_s=3600)
    link.start()
    home, evil = ("10.0.0.9", 14550), ("6.6.6.6", 666)
    hs1 = ground.handshake()
    for raw in hs1[:-5]:  # its tail lost, beyond parity
        air.inject(raw, home)
    air.inject(repair_frame(Op.POKE, 1, (0, 0), 0, None, sysid=9, compid=9), evil)
    sent = len(air.sent)
    clock.advance(0.3)
    link.tick()
    assert {to for _, to in air.sent[sent:]} == {home}
    for raw in hs1[-5:]:
        air.inject(raw, home)
    for raw, _ in air.sent:
        try:
            ground.from_air(raw)
        except SignatureInvalidError:
            continue
    assert ground.session is not None and link._air_peer == home
    command = ground.from_local(_command(400, 1.0))
    for raw in command[:-3]:
        air.inject(raw, home)
    air.inject(command[-3], evil)  # sniffed and relayed first, from its own address
    air.inject(command[-3], home)
    assert link._air_peer == home
    link.stop()


@pytest.mark.parametrize("bps", [7_200, 2_400])
def test_a_slow_radio_completes_a_handshake_with_the_right_key(bps: int) -> None:
    """Review 5b: on a radio where an HS1 takes longer than 10 s (2,400 baud: 31 s), the
    vehicle end keeps its partial HS1 for the HS1's airtime and more, so it arrives whole."""
    made = radio(0.0, bps, seed=1)
    airtime = LINE_BITS * 7_543 / bps
    assert made.start(within_s=4 * airtime) <= 1.2 * airtime
    assert made.vehicle.reassembly.expired == 0


@pytest.mark.parametrize("bps", [7_200, 4_800])
def test_a_slow_radio_repairs_a_handshake_nacked_while_it_was_leaving(bps: int) -> None:
    """Review 5a: one data chunk and every parity chunk of the HS1 lost on a slow radio;
    the vehicle end's NACKs come while the HS1 is still leaving, and the ground end honours
    the last of them once it has left (its copies kept as long): the session comes up.
    (At 2,400 baud an HS1 repaired after it left is older than the vehicle's 30 s HS1
    window: refused as stale, told as delayed.)"""
    clock = ManualClock()
    ground = GroundEnd(
        Initiator("gcs", GCS_KEY, clock), ROBOT_KEM.public_key(), clock=clock, air_bps=bps
    )
    responder = Responder(ROBOT_KEM, {"gcs": GCS_KEY.public_key()}, clock=clock)
    vehicle = VehicleEnd(responder, clock=clock, air_bps=bps)
    frames = ground.handshake()
    chunks = [parse_chunk(parse_frame(raw)) for raw in frames]
    up: list[bytes] = []

    def both_tick() -> None:
        for nack in vehicle.tick():
            up.extend(ground.from_air(nack).air)
        up.extend(ground.tick())

    for raw, chunk in zip(frames, chunks, strict=True):  # paced as the radio carries them
        clock.advance(len(raw) * LINE_BITS / bps)
        if not (chunk.is_parity or chunk.index == 0):
            vehicle.from_air(raw)
        both_tick()
    for _ in range(600):  # a minute more
        clock.advance(0.1)
        both_tick()
        while up:
            out = vehicle.from_air(up.pop(0))
            for raw in out.air:
                ground.from_air(raw)
        if ground.session is not None:
            break
    assert ground.session is not None and ground.repairs["deferred"] > 0
