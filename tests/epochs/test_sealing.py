"""The pure sealed-sample core: framing, the check before crypto, verdicts, the challenge timer.

No DDS, no store, no clock read: values and a manual time in, a verdict or a decision out.
"""

from __future__ import annotations

import os

import pytest

from antireplay.core.errors import (
    Code,
    EpochReplayedError,
    MessageStaleError,
    SignatureInvalidError,
)
from antireplay.epochs import Announcement, EpochPolicy, Kind, Refused, derive_key, parse
from antireplay.epochs.policy import seal, to_ns
from antireplay.epochs.sealing import (
    MAX_INSTANCE,
    ChallengeTimer,
    SampleVerdict,
    accepted,
    check,
    claim,
    claimed_instance,
    frame,
    refused,
    topic_key,
)

PSK = b"sealing-pre-shared-key-0123456789"
PREFIX = bytes(range(8))
NOW = 1_800_000_000.0


def sealed_sample(instance: str, data: bytes, epoch: int = to_ns(NOW), key: bytes = b"") -> bytes:
    """One sealed sample, sealed by hand at a chosen (prefix, epoch)."""
    mac = derive_key(key or topic_key(PSK, "robot/cmd", "octets", 7), Kind.ANNOUNCEMENT)
    return seal(mac, Kind.ANNOUNCEMENT, PREFIX, epoch, frame(instance, data))


def test_topic_key_binds_domain_topic_and_type() -> None:
    keys = {
        topic_key(PSK, "robot/cmd", "octets", 7),
        topic_key(PSK, "robot/cmd", "octets", 8),
        topic_key(PSK, "robot/cmd2", "octets", 7),
        topic_key(PSK, "robot/cmd", "my.Type", 7),
    }
    assert len(keys) == 4
    assert topic_key(PSK, "robot/cmd", "octets", 7) == topic_key(PSK, "robot/cmd", "octets", 7)
    with pytest.raises(ValueError, match="16 bytes"):
        topic_key(b"short", "t", "octets")


def test_frame_carries_the_instance_inside_the_mac() -> None:
    sealed = sealed_sample("arm-1", b"ARM")
    assert claimed_instance(sealed) == "arm-1"
    assert claim(sealed) == (PREFIX, to_ns(NOW))
    with pytest.raises(ValueError, match=str(MAX_INSTANCE)):
        frame("x" * (MAX_INSTANCE + 1), b"")


@pytest.mark.parametrize(
    ("instance", "sealed", "outcome"),
    [
        ("arm", b"\x01" * 10, "malformed"),  # shorter than any sealed sample
        ("arm", b"\x01" * 70_000, "malformed"),  # longer than any announcement
        ("other", sealed_sample("arm", b"ARM"), "wrong_instance"),  # key field moved
    ],
)
def test_check_refuses_before_any_crypto(instance: str, sealed: bytes, outcome: str) -> None:
    verdict = check(instance, sealed)
    assert verdict is not None and verdict.outcome == outcome
    assert verdict.code == Code.INVALID_FRAME and not verdict.authentic


def test_check_passes_a_well_formed_sample_and_records_nothing() -> None:
    sealed = sealed_sample("arm", b"ARM")
    assert check("arm", sealed) is None
    assert check("arm", sealed) is None  # no state: the same answer twice


def test_refused_names_the_outcome_and_keeps_the_claim() -> None:
    sealed = sealed_sample("arm", b"ARM")
    cases = {
        "forged": SignatureInvalidError("announcement tag does not verify"),
        "stale": MessageStaleError("announcement too old"),
        "replayed": EpochReplayedError("epoch already accepted"),
    }
    for outcome, exc in cases.items():
        verdict = refused(exc, "arm", sealed)
        assert (verdict.outcome, verdict.code) == (outcome, exc.code)
        assert (verdict.nonce_prefix, verdict.epoch) == (PREFIX, to_ns(NOW))
        assert verdict.authentic is (outcome != "forged")
    collided = refused(EpochReplayedError("epoch below last"), "arm", sealed, collided=True)
    assert collided.outcome == "prefix_collision" and collided.authentic


def test_a_verdict_names_what_was_refused() -> None:
    verdict = refused(SignatureInvalidError("announcement tag does not verify"), "a", b"\0" * 60)
    assert verdict.named("sample").reason == "sample tag does not verify"
    other = SampleVerdict("malformed", Code.INVALID_FRAME, "bad sealed length", "a")
    assert other.named("sample") is other
    assert other.line() == "REFUSED INVALID_FRAME malformed instance='a' prefix=- epoch=None " + (
        "'bad sealed length'"
    )


def test_judging_with_the_policy_and_a_manual_time() -> None:
    """The core with the pure policy underneath: check, authenticate, admit, commit, decode;
    the same sample again is refused as replayed."""
    key = topic_key(PSK, "robot/cmd", "octets", 7)
    policy = EpochPolicy(key, max_age_ns=to_ns(30), max_forward_ns=to_ns(5), max_prefixes=16)
    sealed = sealed_sample("arm", b"ARM", key=key)
    assert check("arm", sealed) is None
    parsed = parse(sealed, Kind.ANNOUNCEMENT)
    assert policy.authentic(parsed)
    assert policy.check_time(parsed, to_ns(NOW + 1), -1, authentic=True) is None
    assert policy.check_order(parsed, b"", None, authentic=True) is True
    policy.admit(parsed)
    policy.commit(parsed, b"")
    opened = Announcement(parsed.payload, parsed.prefix, parsed.epoch, Kind.ANNOUNCEMENT)
    verdict = accepted("arm", opened)
    assert verdict.accepted and verdict.value == b"ARM" and verdict.line().startswith("ACCEPTED")
    assert policy.last(Kind.ANNOUNCEMENT, PREFIX) == to_ns(NOW)
    again = policy.check_order(parsed, b"", None, authentic=True)
    assert isinstance(again, Refused) and isinstance(again.error, EpochReplayedError)


def test_accepted_decodes_or_refuses_undecodable_data() -> None:
    opened = Announcement(frame("arm", b"12"), PREFIX, 5, Kind.ANNOUNCEMENT)
    assert accepted("arm", opened, int).value == 12
    bad = accepted("arm", Announcement(frame("arm", b"x"), PREFIX, 5, Kind.ANNOUNCEMENT), int)
    assert (bad.outcome, bad.code, bad.value) == ("malformed", Code.INVALID_FRAME, None)


def test_challenge_timer_new_peer_at_once_else_doubling_backoff() -> None:
    timer = ChallengeTimer(retry_s=0.25, retry_max_s=1.0)
    assert timer.due(peers=0, now=100.0)  # the first call always challenges
    assert not timer.due(peers=0, now=100.1)
    assert timer.due(peers=1, now=100.1)  # a new peer may answer: at once
    fired = [t for t in (100.2, 100.4, 100.6, 100.9, 101.0, 101.5, 102.0, 102.9, 103.0)
             if timer.due(peers=1, now=t)]  # fmt: skip
    # delays 0.25 (re-armed by the new peer), then 0.5, 1.0, 1.0 (capped)
    assert fired == [100.4, 100.9, 102.0, 103.0]
    assert not timer.due(peers=0, now=103.1)  # a peer leaving is no reason to ask


def test_random_bytes_never_raise() -> None:
    for size in (0, 1, 43, 44, 45, 60, 300):
        for _ in range(50):
            raw = os.urandom(size)
            verdict = check("arm", raw)
            assert verdict is None or verdict.code == Code.INVALID_FRAME
