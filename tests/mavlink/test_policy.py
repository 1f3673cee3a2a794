"""The MAVLink policy, pure: frames as values and a manual time in, decisions out (no store,
no lock, no clock): accept or refuse, what must be persisted first, the lease arithmetic."""

from __future__ import annotations

import pytest

from antireplay.core.errors import (
    CounterReplayedError,
    MessageFromFutureError,
    MessageStaleError,
    ReplayAttackError,
    SignatureRequiredError,
    StateUnavailableError,
    WrongDirectionError,
    WrongTargetError,
)
from antireplay.core.window import NEVER
from antireplay.mavlink import MAV_EPOCH, UNITS_PER_S, parse_frame
from antireplay.mavlink.codec import Frame
from antireplay.mavlink.policy import (
    HIGH_STEP,
    Facts,
    FrameAdmission,
    MavPolicy,
    Persist,
    RestartFenceError,
    lease_parts,
    lease_value,
)
from harness.mavlink_frames import command_frame, encoder, unsigned_heartbeat

S = UNITS_PER_S
NOW = 300_000 * S  # a manual receiver time, in MAVLink units


def signed(ts: int, *, sysid: int = 255, link_id: int = 1, msgid: int = 76) -> Frame:
    """A signed frame as the policy sees it (authenticity is the driver's)."""
    return Frame(b"", sysid, 190, msgid, b"", True, link_id, ts)


def unsigned(msgid: int, *, version: int = 2, sysid: int = 9) -> Frame:
    return Frame(b"", sysid, 1, msgid, b"", False, version=version)


def accept(policy: MavPolicy, frame: Frame, now: int = NOW) -> None:
    """check, then commit with nothing to persist."""
    policy.check(frame, now)
    assert policy.commit(frame, now) is None


# --- check: records nothing ------------------------------------------------------------------

CHECKS: list[tuple[str, Frame, type[ReplayAttackError] | None]] = [
    ("a fresh signed frame", signed(NOW), None),
    ("a frame 59 s ahead", signed(NOW + 59 * S), None),
    ("a frame 61 s ahead", signed(NOW + 61 * S), MessageFromFutureError),
    ("a new stream 61 s old", signed(NOW - 61 * S, link_id=5), MessageStaleError),
    ("the stream's last, again", signed(NOW - S), CounterReplayedError),
    ("below the stream's last", signed(NOW - 2 * S), CounterReplayedError),
    ("from the vehicle's own system", signed(NOW, sysid=1), WrongDirectionError),
    ("unsigned, allow-listed", unsigned(0), None),
    ("unsigned, not listed", unsigned(76), SignatureRequiredError),
    ("v1, listed unsigned but not as v1", unsigned(0, version=1), SignatureRequiredError),
]


@pytest.mark.parametrize(("what", "frame", "refusal"), CHECKS, ids=[c[0] for c in CHECKS])
def test_check_refuses_from_memory_and_records_nothing(
    what: str, frame: Frame, refusal: type[ReplayAttackError] | None
) -> None:
    policy = MavPolicy(system_id=1, allow_unsigned=frozenset({0}))
    accept(policy, signed(NOW - S))  # the stream (255, 190, 1) is at NOW - 1 s
    before = len(policy.streams), policy.streams.mark(frame.stream)
    if refusal is None:
        policy.check(frame, NOW)
    else:
        with pytest.raises(refusal):
            policy.check(frame, NOW)
    assert (len(policy.streams), policy.streams.mark(frame.stream)) == before
    assert policy.dirty == {}


def test_commit_judges_again_so_of_two_racers_one_passes() -> None:
    policy = MavPolicy()
    frame = signed(NOW)
    policy.check(frame, NOW)
    policy.check(frame, NOW)  # both racers passed check
    assert policy.commit(frame, NOW) is None
    with pytest.raises(CounterReplayedError):
        policy.commit(frame, NOW)


def test_a_reorder_window_takes_late_frames_once() -> None:
    policy = MavPolicy(reorder_window=8)
    for ts in (NOW, NOW + 5, NOW + 3):
        accept(policy, signed(ts))
    with pytest.raises(CounterReplayedError):
        policy.check(signed(NOW + 3), NOW)


ADMISSIONS = [
    ("trusted unsigned v2: sign it", unsigned(0), True, FrameAdmission.SIGN),
    ("trusted unsigned v1: as it came", unsigned(0, version=1), True, FrameAdmission.JUDGE),
    (
        "trusted signed with our id: as it came",
        signed(NOW, link_id=251),
        True,
        FrameAdmission.JUDGE,
    ),
    ("ground unsigned: as it came", unsigned(0), False, FrameAdmission.JUDGE),
    ("ground signed, another id", signed(NOW, link_id=250), False, FrameAdmission.JUDGE),
    ("ground signed with our id", signed(NOW, link_id=251), False, WrongDirectionError),
]


@pytest.mark.parametrize(
    ("what", "frame", "trusted", "answer"), ADMISSIONS, ids=[a[0] for a in ADMISSIONS]
)
def test_admission_of_a_routers_links(
    what: str, frame: Frame, trusted: bool, answer: FrameAdmission | type[ReplayAttackError]
) -> None:
    policy = MavPolicy()
    if isinstance(answer, FrameAdmission):
        assert policy.admit(frame, trusted=trusted, own_link_id=251) is answer
    else:
        with pytest.raises(answer):
            policy.admit(frame, trusted=trusted, own_link_id=251)


def test_bind_refuses_another_vehicles_target_and_direction_learns_from_signed_only() -> None:
    policy = MavPolicy(system_id=1, allow_unsigned=frozenset({0}))
    policy.bind(parse_frame(command_frame(*encoder(), target=1)))
    policy.bind(parse_frame(command_frame(*encoder(), target=0)))  # a broadcast
    with pytest.raises(WrongTargetError):
        policy.bind(parse_frame(command_frame(*encoder(), target=2)))
    policy.bind_direction(parse_frame(unsigned_heartbeat(9)))  # teaches nothing
    policy.check(parse_frame(unsigned_heartbeat(9)), NOW)
    policy.bind_direction(signed(NOW, sysid=9))
    with pytest.raises(WrongDirectionError):
        policy.check(parse_frame(unsigned_heartbeat(9)), NOW)


# --- commit: what must be persisted first ----------------------------------------------------


def claimed(
    policy: MavPolicy, now: int = NOW, found: int | None = None, high: int | None = None
) -> None:
    """The driver's claim, with the store holding ``found`` and ``high``."""
    value = policy.claim(found, high, NEVER, now)
    policy.claimed(value, written=True)


def test_periodic_commit_asks_for_the_claim_the_lookup_and_the_highest_timestamp_in_turn() -> None:
    policy = MavPolicy(stored=True, periodic=True)
    frame = signed(NOW + 3 * S + 1)  # 3 s and 10 µs ahead
    assert policy.commit(frame, NOW) == Persist(claim=True)
    claimed(policy)
    key = "mav:255:190:1"
    assert policy.commit(frame, NOW) == Persist(lookup=key)
    facts = Facts(stored={key: None})
    step = policy.commit(frame, NOW, facts)
    assert step == Persist(high=NOW + 3 * S + HIGH_STEP)  # past the lease: up to the next second
    assert len(policy.streams) == 0 and policy.dirty == {}  # nothing believed before it is durable
    policy.high_persisted(NOW + 3 * S + HIGH_STEP)
    assert policy.commit(frame, NOW, facts) is None
    assert policy.dirty == {key: frame.timestamp}
    assert policy.take_dirty() == {key: frame.timestamp} and policy.dirty == {}


def test_a_stored_high_water_is_the_new_streams_floor() -> None:
    policy = MavPolicy(stored=True, periodic=True)
    claimed(policy)
    key = "mav:255:190:1"
    with pytest.raises(CounterReplayedError, match="persisted stream state"):
        policy.commit(signed(NOW), NOW, Facts(stored={key: NOW}))
    assert policy.commit(signed(NOW + 1), NOW + S, Facts(stored={key: NOW})) is None
    # with a stored value a stream may be older than new_stream_max_age
    old = signed(NOW - 90 * S, link_id=2)
    assert policy.commit(old, NOW, Facts(stored={"mav:255:190:2": NOW - 100 * S})) is None


def test_a_lapsed_lease_is_renewed_before_a_frame_is_accepted() -> None:
    policy = MavPolicy(stored=True, periodic=True, lease_len=2 * S)
    claimed(policy)
    later = NOW + 2 * S + 1
    facts = Facts(stored={"mav:255:190:1": None})
    assert policy.commit(signed(later), later, facts) == Persist(renew=True)
    value = policy.renewal(later)
    assert lease_parts(value) == (1, NOW + 4 * S + 100)  # expiry rounded up to whole ms
    policy.renewed(value, written=True, found=None)
    assert policy.commit(signed(later), later, facts) is None


def test_write_through_advances_each_frame_and_a_refused_advance_is_a_replay() -> None:
    policy = MavPolicy(stored=True, periodic=False)
    key = "mav:255:190:1"
    facts = Facts(stored={key: None})
    assert policy.commit(signed(NOW), NOW, facts) == Persist(through=(key, NOW))
    facts.through = False  # another guard on the store took it
    with pytest.raises(CounterReplayedError, match="already committed"):
        policy.commit(signed(NOW), NOW, facts)
    facts.through = True
    assert policy.commit(signed(NOW), NOW, facts) is None
    assert policy.dirty == {}  # written through: nothing left to flush


def test_a_failed_flush_leaves_its_marks_dirty() -> None:
    policy = MavPolicy()
    policy.dirty = {"a": 5}
    taken = policy.take_dirty()
    policy.dirty["a"] = 3
    policy.restore_dirty(taken)
    assert policy.dirty == {"a": 5}


# --- the lease arithmetic --------------------------------------------------------------------

LEASES = [
    # (stored lease, stored highest timestamp, now, claimed generation or a refusal, fence)
    (None, None, NOW, 1, -1),  # a first run: nothing to fence
    (lease_value(2, NOW - S), None, NOW, 3, NOW - S),  # released cleanly at NOW - 1 s
    (lease_value(2, NOW - S), NOW + 4 * S, NOW, 3, NOW + 4 * S),  # a frame stamped 4 s ahead
    (lease_value(2, NOW - S), NOW - 20 * S, NOW, 3, NOW - S),  # a spike long past: no fence
    (lease_value(1, NOW + S), 0, NOW, StateUnavailableError, None),  # held and live
    (lease_value(1, NOW - S // 10), 0, NOW, StateUnavailableError, None),  # within the skew
    (lease_value(1, NOW - S), 0, NOW, 3, NOW - S),  # a crashed owner's, run out
]


@pytest.mark.parametrize(("found", "high", "now", "claims", "fence"), LEASES)
def test_lease_claims_and_restart_fences(
    found: int | None,
    high: int | None,
    now: int,
    claims: int | type[ReplayAttackError],
    fence: int | None,
) -> None:
    policy = MavPolicy(stored=True, periodic=True, lease_len=2 * S, lease_skew=S // 4)
    if not isinstance(claims, int):
        with pytest.raises(claims):
            policy.claim(found, high, NEVER, now)
        assert policy.generation == 0
        return
    value = policy.claim(found, high, NEVER, now)
    assert policy.generation == 0  # believed only once written
    policy.claimed(value, written=True)
    assert lease_parts(value) == (claims, now + 2 * S)
    assert (policy.generation, policy.lease, policy.restart_fence) == (claims, now + 2 * S, fence)


def restarted(stored: dict[str, int | None], now: int) -> MavPolicy:
    """A new policy (``max_forward`` 20 s) claiming the state ``stored`` at ``now``."""
    again = MavPolicy(stored=True, periodic=True, max_forward=20 * S)
    claimed(again, now, found=stored["mav:lease"], high=stored.get("mav:high"))
    return again


def test_a_clock_spike_fences_only_until_the_wall_clock_passes_it() -> None:
    """The issue's scenario: ``max_forward_s`` 20, one frame accepted 17 s ahead, a clean
    restart long after that moment: honest senders are accepted at once; a restart within
    those 17 s still refuses the spiked frame and everything up to it."""
    policy = MavPolicy(stored=True, periodic=True, max_forward=20 * S)
    claimed(policy)
    spike = signed(NOW + 17 * S, link_id=3)
    facts = Facts(stored={"mav:255:190:3": None})
    step = policy.commit(spike, NOW, facts)
    assert step == Persist(high=NOW + 17 * S)  # made durable before the frame is believed
    policy.high_persisted(NOW + 17 * S)
    assert policy.commit(spike, NOW, facts) is None
    stored = {"mav:high": NOW + 17 * S, "mav:lease": policy.release(NOW + S)}  # a clean stop
    soon = restarted(stored, NOW + 5 * S)  # restarted within the spike
    assert soon.restart_fence == NOW + 17 * S and soon.fence_cause == "high"
    stale = r"1\.00 s below the restart fence \(the previous run accepted a frame stamped 12\.00 s"
    with pytest.raises(RestartFenceError, match=stale):  # how far ahead, said
        soon.check(signed(NOW + 16 * S, link_id=4), NOW + 5 * S)
    later = NOW + 120 * S  # long after the spike's moment
    again = restarted(stored, later)
    honest = signed(later + 1, link_id=5)
    again.check(honest, later)  # not fenced: the fence is a moment long past
    assert again.commit(honest, later, Facts(stored={"mav:255:190:5": None})) is None
    assert again.restart_fence == NOW + 17 * S


def test_honest_senders_never_write_the_highest_timestamp() -> None:
    """Frames stamped within the held lease need no write: the lease's expiry (or, at a clean
    stop, the highest timestamp accepted) fences them."""
    policy = MavPolicy(stored=True, periodic=True, lease_len=2 * S)
    claimed(policy)
    facts = Facts(stored={"mav:255:190:1": None})
    for i in range(100):
        assert policy.commit(signed(NOW + i * S // 100 + S), NOW + i * S // 100, facts) is None
    assert lease_parts(policy.release(NOW + S) or 0)[1] == NOW + S + 99 * S // 100


def test_a_previous_versions_ahead_margin_converts_from_its_own_lease_only() -> None:
    """A state written by the previous version holds ``ahead`` (a margin): converted to that
    version's fence (the expiry of the lease it wrote plus the margin) while ``high`` is
    absent, never once ``high`` exists, whatever newer lease is found; the claim fences there."""
    found = lease_value(2, NOW - 100 * S)
    assert MavPolicy.migration(found, None, 13 * S) == NOW - 87 * S
    assert MavPolicy.migration(found, None, None) is None  # not the previous version's state
    newer = lease_value(3, NOW + 2 * S)  # a claim after ``high`` was written (then a kill)
    assert MavPolicy.migration(newer, NOW - 87 * S, 13 * S) is None
    assert MavPolicy.migration(None, None, 13 * S) == 13 * S  # no lease: the margin alone
    policy = MavPolicy(stored=True, periodic=True)
    policy.claimed(policy.claim(found, NOW - 87 * S, NEVER, NOW), written=True)
    assert policy.restart_fence == NOW - 87 * S and policy.fence_cause == "high"


def test_a_store_that_lost_data_fences_at_the_loss_plus_the_forward_bound() -> None:
    policy = MavPolicy(stored=True, periodic=True, max_forward=60 * S)
    lost_at = MAV_EPOCH + NOW / S - 10  # the store noticed a loss 10 s ago (wall seconds)
    policy.claimed(policy.claim(None, None, lost_at, NOW), written=True)
    assert policy.restart_fence == NOW + 50 * S


def test_a_claim_not_written_and_a_lease_taken_over_fail_closed() -> None:
    policy = MavPolicy(stored=True, periodic=True)
    value = policy.claim(None, None, NEVER, NOW)
    with pytest.raises(StateUnavailableError, match="at once"):
        policy.claimed(value, written=False)
    claimed(policy)
    renewal = policy.renewal(NOW + S)
    policy.renewed(renewal, written=False, found=lease_value(1, NOW + 9 * S))  # ours, later
    assert policy.generation == 1
    with pytest.raises(StateUnavailableError, match="took over"):
        policy.renewed(renewal, written=False, found=lease_value(3, NOW + 9 * S))
    assert (policy.generation, policy.counts["lease_lost"]) == (0, 1)
    with pytest.raises(StateUnavailableError):
        policy.renewal(NOW + S)


def test_release_gives_the_next_even_generation_expiring_at_the_last_acceptance() -> None:
    policy = MavPolicy(stored=True, periodic=True, lease_len=2 * S)
    assert policy.release(NOW) is None  # nothing held
    claimed(policy)
    frame = signed(NOW + S)
    assert policy.commit(frame, NOW + S, Facts(stored={"mav:255:190:1": None})) is None
    assert lease_parts(policy.release(NOW) or 0) == (2, NOW + S)  # accepted at NOW + 1 s
    assert (policy.generation, policy.lease) == (0, -1)
