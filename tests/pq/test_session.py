"""ML-KEM-1024 / ML-DSA-87 sessions with session-bound counters."""

from __future__ import annotations

import pytest
from cryptography.hazmat.primitives.asymmetric import mldsa, mlkem, x25519
from hypothesis import given, settings
from hypothesis import strategies as st

from antireplay import ManualClock
from antireplay.core.counters import NonceCounter
from antireplay.core.errors import (
    CounterReplayedError,
    InvalidFrameError,
    MessageStaleError,
    NonceExhaustedError,
    ReplayAttackError,
    ReplayDetectedError,
    SessionClosedError,
    SignatureInvalidError,
    UnknownSenderError,
    UnknownSessionError,
    WrongDirectionError,
)
from antireplay.pq.session import REKEY_AFTER, Initiator, Purpose, Responder, Session

GCS_KEY = mldsa.MLDSA87PrivateKey.generate()
ROBOT_KEM = mlkem.MLKEM1024PrivateKey.generate()


def pair(clock: ManualClock, max_sessions: int = 256) -> tuple[Initiator, Responder]:
    gcs = Initiator("gcs-1", GCS_KEY, clock)
    robot = Responder(
        ROBOT_KEM, {"gcs-1": GCS_KEY.public_key()}, clock=clock, max_sessions=max_sessions
    )
    return gcs, robot


def connect(gcs: Initiator, robot: Responder) -> tuple[Session, Session, bytes]:
    hs1 = gcs.start(ROBOT_KEM.public_key())
    robot_side, hs2 = robot.accept_handshake(hs1)
    return gcs.finish(hs1, hs2), robot_side, hs1


def test_round_trip_both_directions(clock: ManualClock) -> None:
    gcs_side, robot_side, _ = connect(*pair(clock))
    frame = gcs_side.seal(b"move_forward 1m")
    opened = robot_side.open(frame)
    assert (opened.payload, opened.counter, opened.purpose) == (b"move_forward 1m", 0, Purpose.DATA)
    assert gcs_side.open(robot_side.seal(b"ack")).payload == b"ack"


def test_signed_command_frames(clock: ManualClock) -> None:
    gcs, robot = pair(clock)
    gcs_side, _, _ = connect(gcs, robot)
    frame = gcs_side.seal(b"ARM", Purpose.COMMAND)
    assert robot.open(frame).purpose is Purpose.COMMAND
    with pytest.raises(CounterReplayedError):
        robot.open(frame)


def test_replay_within_session_rejected(clock: ManualClock) -> None:
    gcs, robot = pair(clock)
    gcs_side, _, _ = connect(gcs, robot)
    frame = gcs_side.seal(b"ARM")
    robot.open(frame)
    with pytest.raises(CounterReplayedError):
        robot.open(frame)


def test_reordered_frames_accepted_once_each(clock: ManualClock) -> None:
    gcs_side, robot_side, _ = connect(*pair(clock))
    frames = [gcs_side.seal(f"m{i}".encode()) for i in range(10)]
    order = [3, 0, 1, 9, 2, 8, 4, 7, 5, 6]
    assert [robot_side.open(frames[i]).counter for i in order] == order
    for f in frames:
        with pytest.raises(CounterReplayedError):
            robot_side.open(f)


def test_forged_far_future_counter_changes_no_state(clock: ManualClock) -> None:
    gcs_side, robot_side, _ = connect(*pair(clock))
    real = gcs_side.seal(b"hello")
    forged = bytearray(real)
    forged[20:28] = (2**63).to_bytes(8, "big")  # counter field, tag left as is
    with pytest.raises(SignatureInvalidError):
        robot_side.open(bytes(forged))
    assert robot_side._recv[Purpose.DATA].last == 0
    assert robot_side.open(real).counter == 0
    assert robot_side.open(gcs_side.seal(b"next")).counter == 1


def test_cross_session_replay_rejected(clock: ManualClock) -> None:
    gcs, robot = pair(clock)
    first, _, _ = connect(gcs, robot)
    second, _, _ = connect(gcs, robot)
    captured = first.seal(b"ARM")
    moved = captured[:4] + second.session_id + captured[20:]  # re-address to the new session
    with pytest.raises(SignatureInvalidError):
        robot.open(moved)
    robot.open(captured)  # the original still works once in its own session
    with pytest.raises(CounterReplayedError):
        robot.open(captured)


def test_wrong_direction_and_purpose_fail(clock: ManualClock) -> None:
    gcs, robot = pair(clock)
    gcs_side, robot_side, _ = connect(gcs, robot)
    frame = gcs_side.seal(b"x" * 5_000)
    with pytest.raises(WrongDirectionError):  # MAVLink's code for the same event
        gcs_side.open(frame)  # reflected back to its sender
    with pytest.raises(WrongDirectionError):
        robot.open(robot_side.seal(b"r2i"))  # the responder's own frame, reflected at it
    swapped = bytearray(frame)
    swapped[2] = int(Purpose.COMMAND)
    with pytest.raises(SignatureInvalidError):
        robot_side.open(bytes(swapped))


def test_handshake_replay_rejected_and_never_reuses_keys(clock: ManualClock) -> None:
    gcs, robot = pair(clock)
    hs1 = gcs.start(ROBOT_KEM.public_key())
    session, _ = robot.accept_handshake(hs1)
    with pytest.raises(ReplayDetectedError):
        robot.accept_handshake(hs1)
    clock.advance(40)
    with pytest.raises(MessageStaleError):
        robot.accept_handshake(hs1)
    # Even a responder that lost its seen-set (restart) derives new keys: nonce_r is fresh.
    earlier = ManualClock(clock.wall() - 40)
    peers = {"gcs-1": GCS_KEY.public_key()}
    again, _ = Responder(ROBOT_KEM, peers, clock=earlier).accept_handshake(hs1)
    third, _ = Responder(ROBOT_KEM, peers, clock=earlier).accept_handshake(hs1)
    assert len({session.recv_key, again.recv_key, third.recv_key}) == 3


def test_forged_handshake_leaves_no_state(clock: ManualClock) -> None:
    gcs, robot = pair(clock)
    hs1 = bytearray(gcs.start(ROBOT_KEM.public_key()))
    hs1[-1] ^= 1
    with pytest.raises(SignatureInvalidError):
        robot.accept_handshake(bytes(hs1))
    hs1[-1] ^= 1
    robot.accept_handshake(bytes(hs1))  # the genuine one still opens (no poisoning)


def test_unknown_initiator_and_other_responder_rejected(clock: ManualClock) -> None:
    stranger = Initiator("intruder", mldsa.MLDSA87PrivateKey.generate(), clock)
    _, robot = pair(clock)
    with pytest.raises(UnknownSenderError):
        robot.accept_handshake(stranger.start(ROBOT_KEM.public_key()))
    gcs, _ = pair(clock)
    other_robot = mlkem.MLKEM1024PrivateKey.generate()
    with pytest.raises(InvalidFrameError, match="another responder"):
        robot.accept_handshake(gcs.start(other_robot.public_key()))


def test_tampered_hs2_rejected(clock: ManualClock) -> None:
    gcs, robot = pair(clock)
    hs1 = gcs.start(ROBOT_KEM.public_key())
    _, hs2 = robot.accept_handshake(hs1)
    bad = hs2[:-1] + bytes([hs2[-1] ^ 1])
    with pytest.raises(SignatureInvalidError):
        gcs.finish(hs1, bad)


def test_evicted_session_gets_session_closed(clock: ManualClock) -> None:
    gcs, robot = pair(clock, max_sessions=2)
    first, _, _ = connect(gcs, robot)
    connect(gcs, robot)
    connect(gcs, robot)  # evicts the first (oldest) session with its keys
    assert len(robot) == 2
    with pytest.raises(SessionClosedError):
        robot.open(first.seal(b"late"))


def test_closed_session_gets_session_closed_whatever_happens_later(clock: ManualClock) -> None:
    """One event, one code: later evictions of other sessions do not turn a closed
    session's frames into another code (review finding 7b)."""
    gcs, robot = pair(clock, max_sessions=2)
    connect(gcs, robot)
    gcs_side, robot_side, _ = connect(gcs, robot)
    frame = gcs_side.seal(b"after the rekey")
    robot.close(robot_side)
    for _ in range(4):  # each new session (after the table fills) evicts the oldest
        with pytest.raises(SessionClosedError):
            robot.open(frame)
        connect(gcs, robot)


def test_check_records_nothing(clock: ManualClock) -> None:
    gcs, robot = pair(clock)
    gcs_side, robot_side, _ = connect(gcs, robot)
    frame = gcs_side.seal(b"x")
    robot.check(frame)
    robot.check(frame)
    robot_side.check(frame)
    assert robot_side._recv[Purpose.DATA].last == 0
    robot.open(frame)
    with pytest.raises(CounterReplayedError):
        robot.check(frame)


def test_unknown_session_rejected(clock: ManualClock) -> None:
    gcs_side, _, _ = connect(*pair(clock))
    _, lonely = pair(clock)
    with pytest.raises(UnknownSessionError):
        lonely.open(gcs_side.seal(b"x"))


def test_rekey_threshold_and_hard_limit(clock: ManualClock) -> None:
    gcs_side, robot_side, _ = connect(*pair(clock))
    assert not gcs_side.needs_rekey
    gcs_side._send[Purpose.DATA] = NonceCounter(REKEY_AFTER)
    assert gcs_side.needs_rekey
    robot_side.open(gcs_side.seal(b"x"))
    assert robot_side.needs_rekey
    gcs_side._send[Purpose.DATA] = NonceCounter(2**64 - 2**13 - 2)
    gcs_side.seal(b"last")
    with pytest.raises(NonceExhaustedError):
        gcs_side.seal(b"one too many")


@settings(max_examples=2_000, deadline=None)
@given(st.binary(max_size=200))
def test_fuzzed_frames_are_all_refused_with_typed_errors(data: bytes) -> None:
    with pytest.raises(ReplayAttackError):
        FUZZ_ROBOT.open(data)
    with pytest.raises(ReplayAttackError):
        FUZZ_ROBOT.accept_handshake(data)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 200), st.integers(0, 255))
def test_bit_flips_in_a_real_frame_are_rejected(index: int, mask: int) -> None:
    frame = FUZZ_GCS.seal(b"payload-" + bytes(range(40)))
    index %= len(frame)
    flipped = bytearray(frame)
    flipped[index] ^= mask or 1
    with pytest.raises(ReplayAttackError):
        FUZZ_ROBOT.open(bytes(flipped))


FUZZ_CLOCK = ManualClock()
_g, FUZZ_ROBOT = pair(FUZZ_CLOCK)
FUZZ_GCS, _r, _h = connect(_g, FUZZ_ROBOT)


ROBOT_X25519 = x25519.X25519PrivateKey.generate()


def test_hybrid_handshake_round_trip_and_no_downgrade(clock: ManualClock) -> None:
    gcs = Initiator("gcs-1", GCS_KEY, clock)
    peers = {"gcs-1": GCS_KEY.public_key()}
    hybrid = Responder(ROBOT_KEM, peers, clock=clock, x25519_key=ROBOT_X25519)
    hs1 = gcs.start(ROBOT_KEM.public_key(), ROBOT_X25519.public_key())
    robot_side, hs2 = hybrid.accept_handshake(hs1)
    gcs_side = gcs.finish(hs1, hs2)
    assert robot_side.open(gcs_side.seal(b"ARM", Purpose.COMMAND)).payload == b"ARM"
    with pytest.raises(InvalidFrameError, match="hybrid"):  # a PQ-only HS1: a downgrade
        hybrid.accept_handshake(gcs.start(ROBOT_KEM.public_key()))
    pq_only = Responder(ROBOT_KEM, peers, clock=clock)
    with pytest.raises(InvalidFrameError, match="ML-KEM-1024 only"):
        pq_only.accept_handshake(gcs.start(ROBOT_KEM.public_key(), ROBOT_X25519.public_key()))


def test_hybrid_secret_needs_both_halves(clock: ManualClock) -> None:
    """The wrong X25519 key (same ML-KEM key) derives other keys: HS2 does not confirm."""
    gcs = Initiator("gcs-1", GCS_KEY, clock)
    impostor = x25519.X25519PrivateKey.generate()
    robot = Responder(ROBOT_KEM, {"gcs-1": GCS_KEY.public_key()}, clock=clock, x25519_key=impostor)
    hs1 = gcs.start(ROBOT_KEM.public_key(), ROBOT_X25519.public_key())
    _, hs2 = robot.accept_handshake(hs1)
    with pytest.raises(SignatureInvalidError):
        gcs.finish(hs1, hs2)


def test_hybrid_share_of_low_order_is_refused(clock: ManualClock) -> None:
    """An all-zero X25519 share (a low-order point) is a typed refusal, never a traceback."""
    gcs = Initiator("gcs-1", GCS_KEY, clock)
    robot = Responder(
        ROBOT_KEM, {"gcs-1": GCS_KEY.public_key()}, clock=clock, x25519_key=ROBOT_X25519
    )
    hs1 = bytearray(gcs.start(ROBOT_KEM.public_key(), ROBOT_X25519.public_key()))
    at = 12 + len("gcs-1") + 32 + 1568
    hs1[at : at + 32] = bytes(32)
    body = bytes(hs1[:-4627])
    forged = body + GCS_KEY.sign(body, b"antireplay/v1 hs1")
    with pytest.raises(InvalidFrameError, match="X25519"):
        robot.accept_handshake(forged)


def test_forged_hs2_does_not_cancel_the_handshake(clock: ManualClock) -> None:
    gcs, robot = pair(clock)
    hs1 = gcs.start(ROBOT_KEM.public_key())
    _, hs2 = robot.accept_handshake(hs1)
    with pytest.raises(SignatureInvalidError):
        gcs.finish(hs1, hs2[:-1] + bytes([hs2[-1] ^ 1]))
    gcs.finish(hs1, hs2)  # the genuine HS2 still finishes
    with pytest.raises(UnknownSessionError):
        gcs.finish(hs1, hs2)  # and only once
