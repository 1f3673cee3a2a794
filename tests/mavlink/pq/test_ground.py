"""The PQ ground end (the initiator): its handshake, queue, retries and rekeys."""

from __future__ import annotations

import bisect
import itertools
import os
import random
from typing import Any

import pytest

from antireplay import ManualClock
from antireplay.core.errors import (
    InvalidFrameError,
    ReplayDetectedError,
    SignatureInvalidError,
)
from antireplay.mavlink.codec import parse_frame
from antireplay.mavlink.pq import (
    REKEY_TRANSFERS,
    TRANSFER_LIMIT,
    VehicleEnd,
)
from antireplay.mavlink.pq.repair import EVERYTHING, Op, repair_frame
from antireplay.mavlink.pq.wire import (
    HANDSHAKE_SHARE,
    LINE_BITS,
    MSG_REFUSAL,
    refusal_frame,
)
from antireplay.pq.session import Responder

os.environ["MAVLINK20"] = "1"

from harness.pq_ends import (
    FAST_AIR_BPS,
    GCS_KEY,
    ROBOT_KEM,
    STRANGER_KEY,
    EndPair,
    arm,
    connected,
    plain,
)


def test_queued_commands_go_out_after_the_handshake(clock: ManualClock) -> None:
    link = EndPair(clock)
    hs1 = link.ground.from_local(arm())  # no session yet: queued, the handshake starts
    link.up(hs1)
    assert len(link.commands()) == 1


def test_heartbeats_do_not_push_a_queued_command_out(clock: ManualClock) -> None:
    link = EndPair(clock)
    hs1 = link.ground.from_local(arm())
    beat = plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4))
    for _ in range(50):
        link.ground.from_local(beat)
    link.up(hs1)
    assert len(link.commands()) == 1 and link.ground.unsent == 50


def test_queued_commands_expire_and_every_drop_is_counted(clock: ManualClock) -> None:
    link = EndPair(clock)
    for p in range(10):  # no vehicle: every HS1 is lost, commands queue
        link.ground.from_local(arm(param1=float(p)))
    assert link.ground.drops == {"QUEUE_FULL": 2}
    clock.advance(3)
    link.ground.from_local(arm(param1=10.0))
    clock.advance(3)  # all but the last are older than queue_ttl_s (5 s)
    link.up(link.ground.handshake())
    assert [c.param1 for c in link.commands()] == [10.0]
    assert link.ground.drops == {"QUEUE_FULL": 3, "QUEUE_EXPIRED": 7}
    assert link.ground.unsent == 10


def test_the_ground_end_rekeys_before_its_transfer_numbers_wrap(clock: ManualClock) -> None:
    link = connected(clock)
    link.down(link.vehicle.from_local(plain(lambda m: m.heartbeat_send(2, 3, 0, 0, 4), sysid=1)))
    session = link.ground.session  # it carried vehicle traffic: the budget is full
    beat = plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4))
    first = link.ground.sender.transfer  # where the session began
    link.ground.sender.transfer = first + REKEY_TRANSFERS - 2
    assert len(link.ground.from_local(beat)) == 1
    out = link.ground.from_local(beat)  # the 30,000th transfer: a new handshake goes out
    assert len(out) > 1
    link.ground.sender.transfer = first + TRANSFER_LIMIT  # its HS1 lost meanwhile
    link.ground.from_local(arm())  # no more sending in the old session: queued
    assert link.ground.session is None
    link.up(link.ground.handshake())
    assert link.ground.session is not session and len(link.commands()) == 1


def test_forged_hint_is_ignored_while_telemetry_flows(clock: ManualClock) -> None:
    link = connected(clock)
    link.down(link.vehicle.from_local(plain(lambda m: m.heartbeat_send(2, 3, 0, 0, 4), sysid=1)))
    session = link.ground.session
    assert link.ground.from_air(link.vehicle.hint()[0]).air == []
    assert link.ground.session is session


def test_unknown_local_message_is_refused_before_sealing(clock: ManualClock) -> None:
    link = connected(clock)
    raw = bytearray(plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4)))
    raw[7:10] = (60999).to_bytes(3, "little")  # a message id nobody knows
    with pytest.raises(InvalidFrameError, match="not in the dialect"):
        link.ground.from_local(bytes(raw))


def _misconfigured(clock: ManualClock, refusals_lost: bool = False, **options: Any) -> EndPair:
    """A pair whose ground end signs with a key the vehicle end does not know; its first
    handshake sent (as the link's start sends it)."""
    pair = EndPair(clock)
    if refusals_lost:
        pair.lose_down = lambda raw: parse_frame(raw).msgid == MSG_REFUSAL
    pair.ground = pair.new_ground(STRANGER_KEY, **options)
    pair.up(pair.ground.handshake())
    return pair


def _worst_windows(pair: EndPair, seconds: float, windows: tuple[float, ...]) -> dict[float, int]:
    """Run the pair for ``seconds`` (its first HS1 already sent at 0): the most bytes the
    ground end put on the air within any window of each length."""
    sent = [(0.0, pair.ground_bytes()), *pair.run(seconds, tick_s=0.5)]
    times = [t for t, _ in sent]
    worst = dict.fromkeys(windows, 0)
    for t, total in sent:
        for w in windows:
            before = bisect.bisect_right(times, t - w) - 1
            worst[w] = max(worst[w], total - (sent[before][1] if before >= 0 else 0))
    return worst


WINDOWS = (30.0, 600.0, 1800.0)


@pytest.mark.parametrize("air_bps", [1_200, 7_200, 57_600])
@pytest.mark.parametrize("refusals_lost", [False, True])
def test_a_wrong_signing_key_takes_at_most_five_percent_of_the_air(
    clock: ManualClock, air_bps: int, refusals_lost: bool
) -> None:
    """Finding 4, as the docs state it: over any window of W s (30 s, 10 min, 30 min), a
    misconfigured ground end puts at most 5 % of ``air_bps``/10 times W on the air plus one
    HS1 with its parity, whether its refusals arrive or not (then POKEs run)."""
    pair = _misconfigured(clock, refusals_lost, air_bps=air_bps)
    hs1 = pair.ground_bytes()  # one HS1 with its parity
    worst = _worst_windows(pair, 1_800, WINDOWS)
    for w, most in worst.items():
        assert most <= HANDSHAKE_SHARE * air_bps / LINE_BITS * w + hs1, (w, most, worst)
    assert pair.ground.handshakes["started"] >= 2  # it keeps trying, slowly
    told = 0 if refusals_lost else 1
    assert pair.ground.refusals["verified"] >= told and len(pair.notices) == told


@pytest.mark.parametrize("air_bps", [7_200, 57_600])
def test_an_idle_vehicle_end_keeps_re_handshakes_within_the_budget(
    clock: ManualClock, air_bps: int
) -> None:
    """Review 2: a vehicle end that answers HS1s but relays nothing (its flight controller
    off) makes the ground end hand-shake again after every ``silence_s``; a session that
    carried no vehicle traffic refills nothing, so 10 minutes stay within the budget."""
    pair = EndPair(clock)
    pair.ground = pair.new_ground(air_bps=air_bps)
    pair.up(pair.ground.handshake())
    hs1 = pair.ground_bytes()
    worst = _worst_windows(pair, 600, (600.0,))
    assert worst[600.0] <= HANDSHAKE_SHARE * air_bps / LINE_BITS * 600 + hs1, worst
    assert pair.ground.handshakes["completed"] >= 2  # it did come up, and again


def test_retries_back_off_doubling_with_jitter(clock: ManualClock) -> None:
    """With a budget that never binds (a fast line), the gaps between attempts double from
    ``retry_s`` to ``max_backoff_s``, each shortened by at most a quarter (jitter)."""
    pair = _misconfigured(clock, air_bps=10_000_000, rng=random.Random(7))
    starts, start = [0.0], clock.monotonic()
    for _ in range(2_000):  # 200 s
        pair.run(0.1)
        if pair.ground.handshakes["started"] > len(starts):
            starts.append(clock.monotonic() - start - 0.1)
    gaps = [b - a for a, b in itertools.pairwise(starts)]
    bases = [min(2.0 * 2**n, 60.0) for n in range(len(gaps))]
    assert len(gaps) >= 6, gaps
    for gap, base in zip(gaps, bases, strict=True):
        assert 0.75 * base - 0.1 <= gap <= base + 0.1, (gaps, bases)
    assert len({round(g / b, 2) for g, b in zip(gaps, bases, strict=True)}) > 1  # jittered


def test_only_vehicle_traffic_resets_the_backoff_and_the_budget(clock: ManualClock) -> None:
    pair = _misconfigured(clock)
    pair.run(40)
    pair.responder.peers["gcs"] = STRANGER_KEY.public_key()  # the operator fixes the key
    pair.run(60)
    ground = pair.ground
    assert ground.session is not None
    bucket = ground.budget.bucket
    assert bucket.wait_s(bucket.burst) > 0  # an HS2 alone proves nothing
    pair.down(pair.vehicle.from_local(plain(lambda m: m.heartbeat_send(2, 3, 0, 0, 4), sysid=1)))
    assert bucket.wait_s(bucket.burst) == 0
    assert ground.budget.attempts == 0 and ground.next_attempt_at - ground._hs_quiet <= 2.0


@pytest.mark.parametrize(
    ("option", "value"),
    [("air_bps", 0), ("air_bps", -57_600), ("retry_s", 0.0), ("max_backoff_s", -1.0)],
)
def test_the_ground_end_refuses_budget_parameters_that_are_not_positive(
    clock: ManualClock, option: str, value: float
) -> None:
    with pytest.raises(ValueError, match=f"{option} must be positive"):
        EndPair(clock).new_ground(GCS_KEY, **{option: value})


def _refusal_of(hs1: bytes, transfer: int, key: bytes) -> bytes:
    return refusal_frame(
        hs1, key, transfer=transfer, target=(255, 197), code=1,
        reason="HS1 signature does not verify", sysid=1, compid=197,
    )  # fmt: skip


def test_a_forged_refusal_is_ignored_and_counted(clock: ManualClock) -> None:
    """Nobody without the vehicle's ML-KEM key can make the ground end give up on an
    attempt or log a lie: a refusal of the pending HS1 under any other key is refused
    (``SIGNATURE_INVALID``), counted, and the attempt goes on (it is still poked)."""
    pair = EndPair(clock)
    ground = pair.ground
    ground.handshake()  # lost on the way
    assert ground._pending is not None
    hs1 = ground._pending[0]
    with pytest.raises(SignatureInvalidError):
        ground.from_air(_refusal_of(hs1, ground._hs_transfer, bytes(32)))
    assert ground.refusals == {"forged": 1} and "refused" not in ground.handshakes
    clock.advance(0.6)
    assert ground.tick()  # a POKE: the attempt was not ended by the forgery


def test_a_refusal_of_an_earlier_attempt_is_ignored(clock: ManualClock) -> None:
    """A genuine refusal (the very frame the vehicle end sent) recorded and played back
    against a later attempt: its hash names another HS1, so it is refused as a replay,
    counted, and told nothing."""
    pair, down = EndPair(clock), list[bytes]()

    def record(raw: bytes) -> bool:
        down.append(raw)
        return False  # lose nothing

    pair.lose_down = record
    pair.ground = pair.new_ground(STRANGER_KEY, air_bps=FAST_AIR_BPS)
    pair.up(pair.ground.handshake())
    (notice,) = pair.notices
    (first,) = [raw for raw in down if parse_frame(raw).msgid == MSG_REFUSAL]
    pair.notices.clear()
    clock.advance(2)
    later = pair.ground.tick()  # the second attempt, not delivered
    assert later and pair.ground.handshakes["started"] == 2
    with pytest.raises(ReplayDetectedError):
        pair.ground.from_air(first)
    assert pair.ground.refusals == {"verified": 1, "stale": 1} and not pair.notices
    assert "does not verify" in notice


def test_a_refusal_addressed_to_another_ground_end_is_counted(clock: ManualClock) -> None:
    """Review 9: another ground end's refusal on a shared air changes nothing, and is
    counted (``elsewhere``), never dropped silently."""
    pair = EndPair(clock)
    ground = pair.ground
    ground.handshake()
    assert ground._pending is not None
    hs1 = ground._pending[0]
    other = refusal_frame(
        hs1, bytes(32), transfer=ground._hs_transfer, target=(254, 197), code=1,
        reason="HS1 signature does not verify", sysid=1, compid=197,
    )  # fmt: skip
    assert ground.from_air(other).air == []
    assert ground.refusals == {"elsewhere": 1} and not ground._hs_refused


def test_a_forged_nack_resends_each_hs1_chunk_once_and_never_delays_the_next_try(
    clock: ManualClock,
) -> None:
    """Review 6: an unsigned NACK for the first HS1 (anybody can send one) resends each
    chunk at most once per attempt, and the next attempt comes when it would have."""
    ground = EndPair(clock, air_bps=FAST_AIR_BPS).ground
    hs1 = ground.handshake()  # the vehicle is unreachable
    clock.advance(0.1)
    due = ground.next_attempt_at
    forged = repair_frame(
        Op.NACK, ground._hs_transfer, (255, 197), EVERYTHING, None, sysid=1, compid=197
    )
    assert len(ground.from_air(forged).air) == len(hs1)
    for _ in range(5):
        clock.advance(0.1)
        assert ground.from_air(forged).air == []
    assert ground.next_attempt_at == due
    clock.advance(due - clock.monotonic())
    assert len(ground.tick()) == len(hs1)  # the next attempt, on time
    clock.advance(0.2)  # its budget refilled: a new attempt's chunks may be resent once
    forged = repair_frame(
        Op.NACK, ground._hs_transfer, (255, 197), EVERYTHING, None, sysid=1, compid=197
    )
    assert len(ground.from_air(forged).air) == len(hs1)


def _vehicle_clock(pair: EndPair, clock: ManualClock, skew_s: float) -> ManualClock:
    """Give ``pair`` a vehicle end whose wall clock reads ``skew_s`` ahead of the ground's."""
    ahead = ManualClock(wall=clock.wall() + skew_s, monotonic=clock.monotonic())
    pair.responder = Responder(ROBOT_KEM, {"gcs": GCS_KEY.public_key()}, clock=ahead)
    pair.vehicle = VehicleEnd(pair.responder, clock=ahead)
    return ahead


def test_a_delayed_hs1_is_told_as_delayed_not_as_a_clock_problem(clock: ManualClock) -> None:
    """Review 4: an honest HS1 held 31 s on the link, then delivered (both clocks agree):
    the ground end knows when it left, so it says delayed, not "check both clocks"."""
    pair = EndPair(clock, air_bps=FAST_AIR_BPS)
    ahead = _vehicle_clock(pair, clock, 0.0)
    held = pair.ground.handshake()
    clock.advance(31)
    ahead.advance(31)
    pair.up(held)
    (notice,) = pair.notices
    assert "it was delayed on the link, not a clock problem" in notice, notice
    assert "check both clocks" not in notice


def test_a_stale_hs1_from_disagreeing_clocks_blames_the_clocks(clock: ManualClock) -> None:
    pair = EndPair(clock, air_bps=FAST_AIR_BPS)
    _vehicle_clock(pair, clock, 40.0)
    pair.up(pair.ground.handshake())
    (notice,) = pair.notices
    assert "+40.0 s older than this end's: check both clocks" in notice, notice
