"""Epoch-authenticated announcements: vectors, replay rules, crash safety, collisions."""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import sqlite3
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest
import redis
from hypothesis import given, settings
from hypothesis import strategies as st

from antireplay import ManualClock
from antireplay.audit import AuditLog
from antireplay.core.errors import (
    Code,
    ConfigError,
    EpochReplayedError,
    EpochTooFarAheadError,
    InvalidFrameError,
    MessageStaleError,
    NonceExhaustedError,
    ReplayAttackError,
    SignatureInvalidError,
    StateFileError,
    StateUnavailableError,
    WarningCode,
)
from antireplay.epochs import (
    OUTSTANDING,
    Announcement,
    EpochSigner,
    EpochVerifier,
    Kind,
    derive_key,
    prefix_for_service,
    signer_state,
    successor_prefix,
)
from antireplay.epochs.policy import seal
from antireplay.state import open_store
from antireplay.state.durable import repair
from antireplay.state.redis import RedisStore
from antireplay.state.sqlite import SqliteStore
from harness import assert_never_reused, kill9_runs, started_before
from harness.stores import aged_state, sqlite_store

PSK = b"fleet-pre-shared-key-0123456789ab"


def verifier_on(clock: ManualClock, psk: bytes = PSK, **options: Any) -> EpochVerifier:
    """An in-memory verifier whose start fence is long past (the fence has its own tests)."""
    return started_before(clock, lambda: EpochVerifier(psk, clock=clock, **options))


VECTORS = json.loads((Path(__file__).parents[1] / "vectors" / "epochs.json").read_text())


def hkdf_sha256(ikm: bytes, info: bytes) -> bytes:
    """RFC 5869 written out by hand: a second implementation to check the vectors."""
    prk = hmac.new(b"\0" * 32, ikm, hashlib.sha256).digest()
    return hmac.new(prk, info + b"\x01", hashlib.sha256).digest()


def test_vectors_match_an_independent_implementation() -> None:
    psk = bytes.fromhex(VECTORS["psk"])
    keys = {1: hkdf_sha256(psk, b"antireplay/v1 epoch announcement"),
            2: hkdf_sha256(psk, b"antireplay/v1 epoch binding ping")}  # fmt: skip
    assert keys[1].hex() == VECTORS["keys"]["announcement"]
    assert keys[2].hex() == VECTORS["keys"]["binding ping"]
    for name, prefix in VECTORS["service_prefixes"].items():
        assert hashlib.sha256(b"antireplay/v1 prefix" + name.encode()).digest()[:8].hex() == prefix
    for case in VECTORS["cases"]:
        prefix, payload = bytes.fromhex(case["nonce_prefix"]), bytes.fromhex(case["payload"])
        epoch, kind = case["epoch"].to_bytes(8, "big"), case["kind"]
        tag = hmac.new(keys[kind], payload + prefix + epoch + bytes([1, kind]), "sha256").digest()
        assert (bytes([1, kind]) + prefix + epoch + payload + tag).hex() == case["sealed"]


def test_vectors_open_and_reproduce_with_our_code() -> None:
    psk = bytes.fromhex(VECTORS["psk"])
    clock = ManualClock(wall=1_800_000_000.0)
    verifier = verifier_on(ManualClock(wall=1_800_000_000.0), psk)
    signer = EpochSigner(psk, service_name="discovery-1", clock=clock)
    for case, advance in zip(VECTORS["cases"], [0, 0, 0, 1.0, 0.5], strict=True):
        sealed = bytes.fromhex(case["sealed"])
        got = verifier.open(sealed, kind=Kind(case["kind"]))
        assert got.epoch == case["epoch"]
        clock.advance(advance)
        assert signer.seal(bytes.fromhex(case["payload"]), kind=Kind(case["kind"])) == sealed


def test_round_trip_and_exact_replay(clock: ManualClock) -> None:
    signer, verifier = EpochSigner(PSK, clock=clock), verifier_on(clock)
    sealed = signer.seal(b"participant A")
    got = verifier.open(sealed)
    assert got == Announcement(b"participant A", signer.nonce_prefix, signer.last_epoch)
    with pytest.raises(EpochReplayedError):
        verifier.open(sealed)


def test_older_epoch_after_newer_rejected(clock: ManualClock) -> None:
    signer, verifier = EpochSigner(PSK, clock=clock), verifier_on(clock)
    old, new = signer.seal(b"1"), signer.seal(b"2")
    verifier.open(new)
    with pytest.raises(EpochReplayedError):
        verifier.open(old)
    assert verifier.prefix_collisions == 1  # an authentic unseen older epoch: reported


def test_every_single_bit_flip_is_rejected_and_changes_nothing(clock: ManualClock) -> None:
    signer, verifier = EpochSigner(PSK, clock=clock), verifier_on(clock)
    sealed = signer.seal(b"participant data")
    for i in range(len(sealed) * 8):
        flipped = bytearray(sealed)
        flipped[i // 8] ^= 1 << (i % 8)
        with pytest.raises((SignatureInvalidError, InvalidFrameError)):
            verifier.open(bytes(flipped))
        assert verifier.last(signer.nonce_prefix) is None
    verifier.open(sealed)


def test_bad_tag_with_far_future_epoch_does_not_jam(clock: ManualClock) -> None:
    signer, verifier = EpochSigner(PSK, clock=clock), verifier_on(clock)
    sealed = bytearray(signer.seal(b"x"))
    sealed[10:18] = (2**64 - 2).to_bytes(8, "big")
    with pytest.raises(SignatureInvalidError):
        verifier.open(bytes(sealed))
    verifier.open(signer.seal(b"y"))


def test_authentic_far_future_epoch_is_refused_and_counted(clock: ManualClock) -> None:
    ahead = ManualClock(wall=clock.wall() + 3_600)  # a sender whose clock stepped an hour ahead
    signer = EpochSigner(PSK, clock=ahead)
    verifier = verifier_on(clock, max_forward_s=10)
    with pytest.raises(EpochTooFarAheadError):
        verifier.open(signer.seal(b"from the future"))
    assert verifier.forward_rejections == 1
    assert verifier.last(signer.nonce_prefix) is None  # not locked out


def test_max_age_rejects_old_capture_from_unknown_sender(clock: ManualClock) -> None:
    signer = EpochSigner(PSK, clock=clock)
    captured = signer.seal(b"yesterday")
    clock.advance(86_400)
    verifier = verifier_on(clock, max_age_s=30)
    with pytest.raises(MessageStaleError):
        verifier.open(captured)
    verifier.open(signer.seal(b"today"))


def test_wall_clock_step_back_does_not_regress(clock: ManualClock) -> None:
    """A step back within the forward bound keeps the stream: ``last + 1`` wins."""
    signer = EpochSigner(PSK, clock=clock, max_forward_s=60)
    before = [signer.next_epoch() for _ in range(3)]
    clock.step_wall(-59)
    after = [signer.next_epoch() for _ in range(3)]
    assert before + after == sorted(set(before + after))
    assert after[0] == before[-1] + 1
    assert signer.rotations == 0


def test_forward_glitch_rotates_instead_of_locking_out(
    clock: ManualClock, caplog: pytest.LogCaptureFixture
) -> None:
    """One seal an hour ahead, then NTP corrects: the next seal is accepted at once."""
    signer = EpochSigner(PSK, clock=clock, max_forward_s=30)
    verifier = verifier_on(clock, max_forward_s=30, max_age_s=30)
    old_prefix = signer.nonce_prefix
    before = signer.seal(b"before")
    verifier.open(before)
    clock.step_wall(3_600)
    glitched = signer.seal(b"glitch")
    clock.step_wall(-3_600)  # NTP corrects the clock
    with pytest.raises(EpochTooFarAheadError):
        verifier.open(glitched)
    clock.advance(1)  # one second later, not an hour
    after = verifier.open(signer.seal(b"after"))
    assert after.nonce_prefix == successor_prefix(old_prefix) != old_prefix
    assert after.warning == "EPOCH_SENDER_ROTATED"
    assert verifier.rotations == 1 and verifier.warnings[WarningCode.EPOCH_SENDER_ROTATED] == 1
    assert verifier.forward_rejections == 1
    assert "rotated from nonce_prefix" in caplog.text
    verifier.open(signer.seal(b"and on"))  # the new stream continues; no more warnings
    assert verifier.rotations == 1
    with pytest.raises(EpochReplayedError):  # the old stream keeps its replay protection
        verifier.open(before)


def test_epochs_never_repeat_within_a_prefix_across_glitches(clock: ManualClock) -> None:
    signer = EpochSigner(PSK, clock=clock, max_forward_s=5)
    used: dict[bytes, list[int]] = {}
    for step in (0, 100, -100, 0, 7, -7, 3, -3, 1_000, -1_000, 0):
        clock.step_wall(step)
        for _ in range(3):
            prefix, epoch = signer._next()
            used.setdefault(prefix, []).append(epoch)
    for epochs in used.values():
        assert epochs == sorted(set(epochs))
    assert signer.rotations == 3  # the 100 s, 7 s and 1,000 s glitches; not the 3 s one


def test_glitch_persisted_in_the_state_file_is_recovered_after_restart(
    tmp_path: Path, clock: ManualClock
) -> None:
    """The glitched ceiling reached the state file; the restarted sender rotates at once."""
    path = tmp_path / "signer.state"
    verifier = verifier_on(clock, max_forward_s=30)
    signer = EpochSigner(
        PSK, service_name="svc", state=signer_state(path), clock=clock, max_forward_s=30
    )
    verifier.open(signer.seal(b"before"))
    clock.step_wall(3_600)
    signer.seal(b"glitch")  # ceiling one hour ahead, durably saved
    signer.close()  # the host restarts; NTP corrects the clock
    clock.step_wall(-3_600)
    restarted = EpochSigner(
        PSK, service_name="svc", state=signer_state(path), clock=clock, max_forward_s=30
    )
    got = verifier.open(restarted.seal(b"after restart"))
    assert got.warning == "EPOCH_SENDER_ROTATED"
    assert got.nonce_prefix == successor_prefix(prefix_for_service("svc"))
    restarted.close()
    again = EpochSigner(
        PSK, service_name="svc", state=signer_state(path), clock=clock, max_forward_s=30
    )
    assert again.nonce_prefix == got.nonce_prefix and again.rotations == 1
    assert again.next_epoch() > got.epoch  # the rotated stream resumes above its ceiling
    again.close()
    sealed = EpochSigner(
        PSK, service_name="svc", state=signer_state(path), clock=clock, max_forward_s=30
    ).seal(b"x")
    verifier.open(sealed)


def test_rotation_is_audited(tmp_path: Path, clock: ManualClock) -> None:
    audit = AuditLog(tmp_path / "audit.db")
    signer = EpochSigner(PSK, clock=clock, max_forward_s=10)
    verifier = verifier_on(clock, max_forward_s=10, audit=audit)
    verifier.open(signer.seal(b"a"))
    clock.step_wall(120)
    glitched = signer.seal(b"b")
    clock.step_wall(-120)
    with pytest.raises(EpochTooFarAheadError):
        verifier.open(glitched)
    verifier.open(signer.seal(b"c"))
    rows = [(r.outcome, r.code, r.warning) for r in audit.tail(5)]
    assert rows == [
        ("rejected", "EPOCH_TOO_FAR_AHEAD", None),
        ("accepted", None, "EPOCH_SENDER_ROTATED"),
    ]
    audit.close()


def test_rotation_recognised_by_a_restarted_verifier(tmp_path: Path, clock: ManualClock) -> None:
    path = f"sqlite:{aged_state(tmp_path / 'verifier.db', clock)}"
    signer = EpochSigner(PSK, clock=clock, max_forward_s=10)
    verifier = EpochVerifier(PSK, clock=clock, store=open_store(path, clock=clock))
    verifier.open(signer.seal(b"a"))
    verifier.store.close()
    clock.step_wall(60)
    signer.seal(b"lost")
    clock.step_wall(-60)
    restarted = EpochVerifier(PSK, clock=clock, store=open_store(path, clock=clock))
    assert restarted.open(signer.seal(b"b")).warning == "EPOCH_SENDER_ROTATED"
    restarted.store.close()


def rotated(clock: ManualClock, signer: EpochSigner, verifier: EpochVerifier) -> None:
    """One epoch accepted, then the signer's clock 30 s ahead for one seal and back: its
    next epoch starts the successor prefix, and the verifier reports the rotation."""
    verifier.open(signer.seal(b"a"))
    clock.step_wall(30)
    signer.seal(b"glitched, never delivered")
    clock.step_wall(-30)
    clock.advance(1)
    assert verifier.open(signer.seal(b"b")).warning == "EPOCH_SENDER_ROTATED"


def test_rotation_is_reported_once_not_after_each_restart(
    tmp_path: Path, clock: ManualClock
) -> None:
    """A verifier restarted on its store does not report a rotation it already reported
    (review finding 6): the warning is for the new prefix's first epoch in the store."""
    path = f"sqlite:{aged_state(tmp_path / 'verifier.db', clock)}"
    signer = EpochSigner(PSK, clock=clock, max_forward_s=10)
    verifier = EpochVerifier(PSK, clock=clock, store=open_store(path, clock=clock))
    rotated(clock, signer, verifier)
    verifier.store.close()
    for _ in range(2):
        clock.advance(1)
        restarted = EpochVerifier(PSK, clock=clock, store=open_store(path, clock=clock))
        assert restarted.open(signer.seal(b"c")).warning is None
        assert (restarted.rotations, sum(restarted.warnings.values())) == (0, 0)
        restarted.store.close()


def test_rotation_is_not_reported_again_after_eviction(clock: ManualClock) -> None:
    """A rotated prefix evicted from the table and admitted again is not a new rotation."""
    verifier = verifier_on(clock, max_prefixes=1, max_forward_s=10)
    signer, other = EpochSigner(PSK, clock=clock, max_forward_s=10), EpochSigner(PSK, clock=clock)
    rotated(clock, signer, verifier)
    clock.advance(1)
    verifier.open(other.seal(b"x"))  # evicts the rotated prefix
    clock.advance(1)
    assert verifier.open(signer.seal(b"c")).warning is None  # admitted again, above the fence
    assert verifier.rotations == 1


def test_refused_new_prefix_evicts_no_live_sender(tmp_path: Path, clock: ManualClock) -> None:
    """An authentic new prefix at or below the lowest held epoch of a full table is refused
    and changes nothing: the live senders stay, no fence rises (review finding 5)."""
    store = open_store(f"sqlite:{aged_state(tmp_path / 'v.db', clock)}", clock=clock)
    verifier = EpochVerifier(PSK, clock=clock, store=store, max_prefixes=2)
    a, b = EpochSigner(PSK, clock=clock), EpochSigner(PSK, clock=clock)
    behind = ManualClock(wall=clock.wall() - 0.001)  # a sender 1 ms behind the others
    lagging = EpochSigner(PSK, clock=behind)
    verifier.open(a.seal(b"a"))
    verifier.open(b.seal(b"b"))
    late = lagging.seal(b"c")
    verifier.check(late)  # above the fence; the full-table test is the commit's
    with pytest.raises(MessageStaleError, match="lowest mark") as refused:
        verifier.open(late)
    assert refused.value.detail == "fence"
    table = verifier.policy.tables[Kind.ANNOUNCEMENT]
    assert (a.nonce_prefix in table, b.nonce_prefix in table) == (True, True)
    assert (table.fence, table.evictions) == (-1, 0)
    assert verifier.store.current("epoch:announcement:floor") is None
    clock.advance(1)
    behind.advance(1)
    verifier.open(lagging.seal(b"d"))  # later, above the lowest mark: now one is evicted...
    assert table.evictions == 1
    assert verifier.store.current("epoch:announcement:floor") == table.fence  # ...persisted
    verifier.store.close()


def test_signer_bound_must_exceed_its_reservation() -> None:
    with pytest.raises(ValueError, match="reserve_s"):
        EpochSigner(PSK, reserve_s=5, max_forward_s=5)


def test_pings_use_a_separate_key(clock: ManualClock) -> None:
    signer, verifier = EpochSigner(PSK, clock=clock), verifier_on(clock)
    ping = signer.seal_ping(b"bind")
    assert verifier.open_ping(ping).kind is Kind.PING
    with pytest.raises(InvalidFrameError):
        verifier.open(ping)
    relabeled = bytes([1, 1]) + ping[2:]
    with pytest.raises(SignatureInvalidError):
        verifier.open(relabeled)
    with pytest.raises(EpochReplayedError):
        verifier.open_ping(ping)


def test_replayed_announcement_cannot_renew_a_lease(clock: ManualClock) -> None:
    """The lease table is renewed only with what open() returns."""
    signer, verifier = EpochSigner(PSK, clock=clock), verifier_on(clock)
    leases: dict[bytes, float] = {}
    first = signer.seal(b"alive")
    leases[verifier.open(first).nonce_prefix] = clock.wall() + 10
    clock.advance(20)  # participant died; attacker replays its old announcement
    with pytest.raises(EpochReplayedError):
        leases[verifier.open(first).nonce_prefix] = clock.wall() + 10
    assert leases[signer.nonce_prefix] < clock.wall()


def test_prefix_collision_reported(clock: ManualClock, caplog: pytest.LogCaptureFixture) -> None:
    a = EpochSigner(PSK, service_name="ds", clock=clock)
    b = EpochSigner(PSK, service_name="ds", clock=ManualClock(wall=clock.wall() - 5))
    verifier = verifier_on(clock)
    verifier.open(a.seal(b"a1"))
    clock.advance(1)
    verifier.open(a.seal(b"a2"))
    with pytest.raises(EpochReplayedError, match="collision"):
        verifier.open(b.seal(b"b1"))
    assert verifier.prefix_collisions == 1
    assert "used by two senders" in caplog.text
    assert prefix_for_service("ds").hex() in caplog.text


def test_prefix_table_is_bounded_and_fenced(clock: ManualClock) -> None:
    verifier = verifier_on(clock, max_prefixes=3)
    signers = [EpochSigner(PSK, clock=clock) for _ in range(4)]
    first = [s.seal(b"hi") for s in signers]
    for sealed in first[:3]:
        verifier.open(sealed)
    clock.advance(1)
    verifier.open(signers[3].seal(b"hi"))  # evicts the oldest prefix, the fence rises
    with pytest.raises(MessageStaleError) as refused:
        verifier.open(first[0])
    assert refused.value.detail == "fence"  # one code for this event everywhere


def test_sender_restart_with_state_file_keeps_increasing(tmp_path: Path) -> None:
    frozen = ManualClock(wall=1_000.0)
    path = tmp_path / "signer.state"
    a = EpochSigner(PSK, service_name="svc", state=signer_state(path), clock=frozen)
    emitted = [a.next_epoch() for _ in range(10)]
    a.close()
    b = EpochSigner(
        PSK, service_name="svc", state=signer_state(path), clock=frozen
    )  # "host reboot"
    assert b.next_epoch() > max(emitted)
    assert b.nonce_prefix == a.nonce_prefix


def test_random_prefix_is_kept_across_restart(tmp_path: Path, clock: ManualClock) -> None:
    path = tmp_path / "signer.state"
    a = EpochSigner(PSK, state=signer_state(path), clock=clock)
    a.seal(b"x")
    a.close()
    b = EpochSigner(PSK, state=signer_state(path), clock=clock)
    assert b.nonce_prefix == a.nonce_prefix
    b.close()
    with pytest.raises(StateFileError, match="another nonce_prefix"):
        EpochSigner(PSK, state=signer_state(path), clock=clock, nonce_prefix=b"\0" * 8)


def test_block_reservation_writes_rarely(tmp_path: Path) -> None:
    clock = ManualClock(wall=1_000.0)
    signer = EpochSigner(PSK, state=signer_state(tmp_path / "s"), clock=clock, reserve_s=1.0)
    for _ in range(1_000):
        clock.advance(0.01)
        signer.seal(b"busy")
    assert 9 <= signer._epochs.reservations <= 11


def test_sender_kill9_at_random_moments_never_repeats(tmp_path: Path) -> None:
    args = ["-m", "harness.workers.epoch_worker", str(tmp_path / "signer.state"), "0.000002"]
    assert_never_reused(kill9_runs(args, 100, 150, seed=99), "sender")


def test_verifier_restart_rejects_everything_old(tmp_path: Path, clock: ManualClock) -> None:
    spec = f"sqlite:{aged_state(tmp_path / 'verifier.db', clock)}"
    signer = EpochSigner(PSK, clock=clock)
    sent = [signer.seal(f"a{i}".encode()) for i in range(5)]
    verifier = EpochVerifier(
        PSK, store=open_store(spec, clock=clock), clock=clock
    )  # a deployment started earlier
    for sealed in sent[::2]:
        verifier.open(sealed)  # accept 0, 2, 4; 1 and 3 are superseded
    verifier.store.close()
    restarted = EpochVerifier(PSK, store=open_store(spec, clock=clock), clock=clock)
    for sealed in sent:
        with pytest.raises(EpochReplayedError):
            restarted.open(sealed)
    restarted.open(signer.seal(b"fresh"))
    restarted.store.close()


def test_each_accept_is_one_store_advance(tmp_path: Path, clock: ManualClock) -> None:
    store = sqlite_store(tmp_path / "verifier.db", clock=clock)
    signer = EpochSigner(PSK, clock=clock)
    verifier = EpochVerifier(PSK, store=store, clock=clock)
    verifier.open(signer.seal(b"first"))  # a new prefix: its epoch and its successor's mark
    advances: list[str] = []
    advance = store.advance_above

    def counted(key: str, value: int, fence_key: str | None) -> bool:
        advances.append(key)
        return advance(key, value, fence_key)

    store.advance_above = counted  # type: ignore[method-assign]
    for i in range(5):
        clock.advance(0.001)
        verifier.open(signer.seal(f"more {i}".encode()))
    assert len(advances) == 5 and len(set(advances)) == 1
    store.close()


def test_memory_store_verifier_refuses_what_was_sealed_before_it_started(
    clock: ManualClock,
) -> None:
    """Issue 18: without persistent state a verifier cannot know what a previous process
    accepted, so it fences at its start (plus max_forward_s), as the replay cache does."""
    signer = EpochSigner(PSK, clock=clock)
    captured = signer.seal(b"sealed before the restart")
    verifier = EpochVerifier(PSK, clock=clock, max_forward_s=5)
    with pytest.raises(MessageStaleError) as refused:
        verifier.open(captured)
    assert refused.value.detail == "restart_fence"
    clock.advance(5.001)
    verifier.open(signer.seal(b"after the fence"))


def test_verifier_on_a_store_that_lost_its_state_fences(tmp_path: Path, clock: ManualClock) -> None:
    db = aged_state(tmp_path / "verifier.db", clock)
    signer = EpochSigner(PSK, clock=clock)
    verifier = EpochVerifier(
        PSK, store=open_store(f"sqlite:{db}", clock=clock), clock=clock, max_forward_s=5
    )
    old = signer.seal(b"old")
    verifier.open(old)
    verifier.store.close()
    db.unlink()  # the database is gone; its witness remains: loss is detected, not forgotten
    clock.advance(1)
    restarted = EpochVerifier(
        PSK, store=open_store(f"sqlite:{db}", clock=clock), clock=clock, max_forward_s=5
    )
    with pytest.raises(MessageStaleError, match="before this verifier's state began"):
        restarted.open(old)
    clock.advance(6)
    restarted.open(signer.seal(b"after the fence"))
    restarted.store.close()


def test_two_verifiers_on_one_store_accept_each_epoch_once(
    tmp_path: Path, clock: ManualClock
) -> None:
    spec = f"sqlite:{aged_state(tmp_path / 'shared.db', clock)}"
    signer = EpochSigner(PSK, clock=clock)
    first = EpochVerifier(PSK, store=open_store(spec, clock=clock), clock=clock)
    second = EpochVerifier(PSK, store=open_store(spec, clock=clock), clock=clock)
    sealed = signer.seal(b"once")
    first.open(sealed)
    with pytest.raises(EpochReplayedError):
        second.open(sealed)
    first.store.close()
    second.store.close()


def test_check_records_nothing_and_counts_nothing(clock: ManualClock) -> None:
    ahead = EpochSigner(PSK, clock=ManualClock(wall=clock.wall() + 3_600))
    signer, verifier = EpochSigner(PSK, clock=clock), verifier_on(clock, max_forward_s=10)
    sealed = signer.seal(b"x")
    verifier.check(sealed)
    verifier.check(sealed)
    assert verifier.last(signer.nonce_prefix) is None
    with pytest.raises(EpochTooFarAheadError):
        verifier.check(ahead.seal(b"y"))
    assert verifier.forward_rejections == 0  # unauthenticated: no evidence, nothing counted
    verifier.open(sealed)
    with pytest.raises(EpochReplayedError):
        verifier.check(sealed)


def test_bounds_are_validated_never_clamped() -> None:
    with pytest.raises(ConfigError, match="max_forward_s"):
        EpochVerifier(PSK, max_forward_s=0.0)
    with pytest.raises(ConfigError, match="max_age_s"):
        EpochVerifier(PSK, max_age_s=float("inf"))


def test_signer_exhaustion_is_its_own_not_a_peer_rejection() -> None:
    signer = EpochSigner(PSK, clock=ManualClock(wall=1.9e10))  # 2**64 ns is year 2554
    with pytest.raises(NonceExhaustedError):
        signer.seal(b"x")


def test_damaged_signer_state_refused_then_repaired_above(tmp_path: Path) -> None:
    path = tmp_path / "signer.state"
    frozen = ManualClock(wall=1_000.0)
    signer = EpochSigner(PSK, state=signer_state(path), clock=frozen, reserve_s=5)
    emitted = [signer.next_epoch() for _ in range(3)]
    signer.close()
    path.write_bytes(b"\0" * 20)
    with pytest.raises(StateFileError):
        EpochSigner(PSK, state=signer_state(path), clock=frozen)
    repair(path, "epoch-signer", now_ns=0)
    with pytest.raises(StateFileError, match="another nonce_prefix"):
        EpochSigner(PSK, state=signer_state(path), clock=frozen, nonce_prefix=signer.nonce_prefix)
    again = EpochSigner(PSK, state=signer_state(path), clock=ManualClock(wall=2_000.0))
    assert again.next_epoch() > max(emitted)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.tuples(st.just("send"), st.integers(0, 2)),
            st.tuples(st.just("replay"), st.integers(0, 1_000)),
            st.tuples(st.just("restart"), st.integers(0, 2)),
            st.tuples(st.just("tick"), st.integers(0, 3)),
        ),
        max_size=60,
    )
)
def test_property_each_prefix_epoch_accepted_at_most_once(ops: list[tuple[str, int]]) -> None:
    clock = ManualClock(wall=1_000.0)
    signers = [EpochSigner(PSK, nonce_prefix=bytes([i]) * 8, clock=clock) for i in range(3)]
    verifier = verifier_on(clock)
    sent: list[bytes] = []
    accepted: set[tuple[bytes, int]] = set()
    for op, arg in ops:
        if op == "send":
            sent.append(signers[arg].seal(b"pa"))
            candidate = sent[-1]
        elif op == "replay" and sent:
            candidate = sent[arg % len(sent)]
        elif op == "restart":  # a process restart without state: wall anchoring keeps order
            signers[arg] = EpochSigner(PSK, nonce_prefix=bytes([arg]) * 8, clock=clock)
            continue
        else:
            clock.advance(arg / 1000)
            continue
        try:
            got = verifier.open(candidate)
        except ReplayAttackError:
            continue
        key = (got.nonce_prefix, got.epoch)
        assert key not in accepted
        accepted.add(key)


class _FlakySqlite(SqliteStore):
    """A real SQLite store whose writes fail while ``down`` (a full disk, a lost mount)."""

    down = False
    forget_down = False

    def advance_above(self, key: str, value: int, fence_key: str | None) -> bool:
        if self.down:
            raise StateUnavailableError(f"sqlite {self.path}: disk I/O error")
        return super().advance_above(key, value, fence_key)

    def forget(self, keys: Sequence[str], fence_key: str, fence: int) -> None:
        if self.down or self.forget_down:
            raise StateUnavailableError(f"sqlite {self.path}: disk I/O error")
        super().forget(keys, fence_key, fence)


def test_failed_store_write_moves_no_mark_and_redelivery_is_accepted(
    tmp_path: Path, clock: ManualClock, caplog: pytest.LogCaptureFixture
) -> None:
    store = started_before(clock, lambda: _FlakySqlite(tmp_path / "verifier.db", clock=clock))
    signer, verifier = EpochSigner(PSK, clock=clock), EpochVerifier(PSK, store=store, clock=clock)
    first = verifier.open(signer.seal(b"first"))
    clock.advance(0.001)
    second = signer.seal(b"second")
    store.down = True
    with pytest.raises(StateUnavailableError):
        verifier.open(second)
    assert verifier.last(signer.nonce_prefix) == first.epoch  # never believed what failed
    store.down = False
    got = verifier.open(second)  # the genuine redelivery, once the store is back
    assert got.payload == b"second" and verifier.last(signer.nonce_prefix) == got.epoch
    assert verifier.prefix_collisions == 0 and "collision" not in caplog.text
    store.close()


def test_failed_first_write_of_a_new_prefix_leaves_it_unknown(
    tmp_path: Path, clock: ManualClock
) -> None:
    store = started_before(clock, lambda: _FlakySqlite(tmp_path / "verifier.db", clock=clock))
    signer, verifier = EpochSigner(PSK, clock=clock), EpochVerifier(PSK, store=store, clock=clock)
    sealed = signer.seal(b"hello")
    store.down = True
    with pytest.raises(StateUnavailableError):
        verifier.open(sealed)
    assert verifier.last(signer.nonce_prefix) is None
    store.down = False
    assert verifier.open(sealed).payload == b"hello"
    store.close()


def _poison_sqlite(db: Path, key: str) -> None:
    with sqlite3.connect(db) as conn:
        conn.execute("INSERT OR REPLACE INTO counters VALUES (?, 'x')", (key,))
    conn.close()


def test_wrong_typed_floor_in_sqlite_refuses_start_naming_the_file(
    tmp_path: Path, clock: ManualClock
) -> None:
    db = aged_state(tmp_path / "verifier.db", clock)
    EpochVerifier(PSK, store=open_store(f"sqlite:{db}", clock=clock), clock=clock).store.close()
    _poison_sqlite(db, "epoch:announcement:floor")
    store = sqlite_store(db, clock=clock)
    with pytest.raises(StateFileError) as refused:
        store.current("epoch:announcement:floor")
    assert str(db) in str(refused.value) and refused.value.recovery
    with pytest.raises(StateFileError, match=str(db)):
        EpochVerifier(PSK, store=store, clock=clock)
    with pytest.raises(StateFileError):
        store.advance("epoch:announcement:floor", 5)
    store.close()


def test_wrong_typed_epoch_while_running_is_state_unavailable(
    tmp_path: Path, clock: ManualClock
) -> None:
    db = aged_state(tmp_path / "verifier.db", clock)
    signer = EpochSigner(PSK, clock=clock)
    verifier = EpochVerifier(PSK, store=open_store(f"sqlite:{db}", clock=clock), clock=clock)
    _poison_sqlite(db, f"epoch:announcement:{signer.nonce_prefix.hex()}")
    with pytest.raises(StateUnavailableError, match=str(db)):
        verifier.open(signer.seal(b"hello"))
    assert verifier.last(signer.nonce_prefix, Kind.PING) is None
    verifier.store.close()


def test_wrong_typed_value_in_redis_is_a_state_file_error(
    redis_url: str, clock: ManualClock
) -> None:
    prefix = f"poison{uuid.uuid4().hex}:"
    store = RedisStore(redis_url, prefix=prefix, clock=clock)
    EpochVerifier(PSK, store=store, clock=clock)
    raw = redis.Redis.from_url(redis_url)
    raw.set(f"{prefix}{{antireplay}}:c:epoch:announcement:floor", "x")
    with pytest.raises(StateFileError) as refused:
        EpochVerifier(PSK, store=store, clock=clock)
    assert redis_url in str(refused.value) and refused.value.recovery
    with pytest.raises(StateFileError, match=redis_url):
        store.advance("epoch:announcement:floor", 5)
    raw.close()
    store.close()


def fresh_pair(clock: ManualClock, **options: Any) -> tuple[EpochSigner, EpochVerifier, bytes]:
    """A signer that has been sealing for a while, a verifier that just started without
    state (its start fence ahead), and a sample captured before that start."""
    signer = EpochSigner(PSK, clock=clock)
    captured = signer.seal(b"captured before the verifier started")
    clock.advance(0.5)
    return signer, EpochVerifier(PSK, clock=clock, **options), captured


def refused_by_fence(verifier: EpochVerifier, sealed: bytes) -> bool:
    with pytest.raises(MessageStaleError) as refused:
        verifier.open(sealed)
    return refused.value.detail == "restart_fence"


@pytest.mark.parametrize("forward_s", [5.0, 60.0])
def test_answered_challenge_opens_the_fence_above_the_answer_at_once(
    clock: ManualClock, forward_s: float
) -> None:
    signer, verifier, captured = fresh_pair(clock, max_forward_s=forward_s)
    challenge = verifier.challenge()
    assert challenge is not None
    in_flight = signer.seal(b"sealed after the challenge, before the answer")
    answered = verifier.open_answer(signer.answer(challenge))
    assert (answered.nonce_prefix, answered.kind) == (signer.nonce_prefix, Kind.ANSWER)
    clock.advance(0.001)  # no waiting for the fence: one millisecond later
    assert verifier.open(signer.seal(b"fresh")).payload == b"fresh"
    assert refused_by_fence(verifier, captured)  # its epoch is below the answered one
    assert refused_by_fence(verifier, in_flight)
    other = EpochSigner(PSK, clock=clock)  # a writer that did not answer stays fenced
    assert refused_by_fence(verifier, other.seal(b"unanswered prefix"))


def test_without_an_answer_the_start_fence_holds_as_before(clock: ManualClock) -> None:
    signer, verifier, captured = fresh_pair(clock, max_forward_s=5)
    assert verifier.challenge() is not None  # nobody answers
    assert refused_by_fence(verifier, signer.seal(b"during the fence"))
    clock.advance(5.001)
    assert verifier.challenge() is None  # past the fence there is nothing to prove
    assert verifier.open(signer.seal(b"after the fence")).payload == b"after the fence"
    with pytest.raises(MessageStaleError):
        verifier.open(captured)


def test_answer_to_a_stale_nonce_is_refused_and_changes_nothing(clock: ManualClock) -> None:
    signer, verifier, _ = fresh_pair(clock)
    earlier_run = EpochVerifier(PSK, clock=clock)  # a previous run's challenge, captured
    old_challenge = earlier_run.challenge()
    assert old_challenge is not None
    replayed_answer = signer.answer(old_challenge)
    assert verifier.challenge() is not None
    with pytest.raises(MessageStaleError) as refused:
        verifier.open_answer(replayed_answer)
    assert refused.value.detail == "challenge_nonce"
    assert verifier.policy.answered == {}
    assert refused_by_fence(verifier, signer.seal(b"still fenced"))


def test_outstanding_nonces_are_bounded(clock: ManualClock) -> None:
    signer, verifier, _ = fresh_pair(clock)
    first = verifier.challenge()
    assert first is not None
    for _ in range(OUTSTANDING):  # retries, each with a new nonce
        assert verifier.challenge() is not None
    assert len(verifier.policy.nonces) == OUTSTANDING
    with pytest.raises(MessageStaleError):
        verifier.open_answer(signer.answer(first))


@pytest.mark.parametrize("index", [1, 5, 12, 20, -1])  # kind, prefix, epoch, nonce, tag
def test_forged_answer_is_refused_and_changes_nothing(clock: ManualClock, index: int) -> None:
    signer, verifier, _ = fresh_pair(clock)
    challenge = verifier.challenge()
    assert challenge is not None
    answer = bytearray(signer.answer(challenge))
    answer[index] ^= 0x01
    with pytest.raises((SignatureInvalidError, InvalidFrameError, MessageStaleError)):
        verifier.open_answer(bytes(answer))
    stranger = EpochSigner(os.urandom(32), nonce_prefix=signer.nonce_prefix, clock=clock)
    with pytest.raises(SignatureInvalidError):  # a stranger's key: the challenge's MAC fails
        stranger.answer(challenge)
    with pytest.raises(SignatureInvalidError):  # and an answer under it fails here
        verifier.open_answer(seal(derive_key(os.urandom(32), Kind.PING), Kind.ANSWER,
                                  signer.nonce_prefix, 1, challenge[18:-32]))  # fmt: skip
    assert verifier.policy.answered == {}
    assert refused_by_fence(verifier, signer.seal(b"still fenced"))


def test_signer_answers_only_authentic_timely_challenges(clock: ManualClock) -> None:
    signer, verifier, _ = fresh_pair(clock, max_forward_s=5)
    challenge = verifier.challenge()
    assert challenge is not None
    last = signer.last_epoch
    forged = bytearray(challenge)
    forged[-1] ^= 1
    with pytest.raises(SignatureInvalidError):
        signer.answer(bytes(forged))
    with pytest.raises(InvalidFrameError):
        signer.answer(signer.seal_ping(b"a ping is no challenge"))
    last = signer.last_epoch
    clock.advance(61)  # a challenge replayed a minute later gets no answer
    with pytest.raises(MessageStaleError):
        signer.answer(challenge)
    assert signer.last_epoch == last  # refused challenges spend no epoch


class _FencedAt:
    """A store that has just reported a loss: its fence is ``at``; all else is ``store``'s
    (a wrapper, so that it works on the compiled store as on the sources)."""

    def __init__(self, store: Any, at: float) -> None:
        self._store, self._at = store, at

    def fence(self) -> float:
        return self._at

    def __getattr__(self, name: str) -> Any:
        return getattr(self._store, name)


def test_a_store_that_loses_state_voids_the_answers(clock: ManualClock) -> None:
    """Answers prove freshness against the state the verifier had when it asked: a store
    that reports a loss afterwards (a new fence) puts every prefix back on the fence."""
    signer, verifier, _ = fresh_pair(clock)
    challenge = verifier.challenge()
    assert challenge is not None
    verifier.open_answer(signer.answer(challenge))
    accepted = signer.seal(b"accepted before the loss")
    verifier.open(accepted)
    clock.advance(1)
    lost_at = clock.wall()
    verifier.store = _FencedAt(verifier.store, lost_at)
    assert refused_by_fence(verifier, signer.seal(b"after the loss"))
    with pytest.raises(MessageStaleError):  # the old nonce is void too
        verifier.open_answer(signer.answer(challenge))
    assert verifier.policy.answered == {}


def _stored_counters(store: SqliteStore) -> dict[str, str]:
    """Every counter the SQLite file holds (read-only, on a connection of its own)."""
    db = sqlite3.connect(f"file:{store.path}?mode=ro", uri=True)
    try:
        return dict(db.execute("SELECT key, value FROM counters").fetchall())
    finally:
        db.close()


def test_forgotten_prefixes_leave_no_counters_and_stay_refused(
    tmp_path: Path, clock: ManualClock
) -> None:
    """Many more authentic prefixes than the table holds: the store keeps a bounded number
    of counters (the table's prefixes, their markers, the floor), and every forgotten
    prefix's epoch is still refused, by this verifier and by one restarted on the file."""
    table, senders = 4, 60
    store = sqlite_store(tmp_path / "verifier.db", clock=clock)
    verifier = EpochVerifier(PSK, store=store, clock=clock, max_prefixes=table)
    sent = []
    for _ in range(senders):
        clock.advance(0.01)
        sealed = EpochSigner(PSK, clock=clock).seal(b"hi")
        verifier.open(sealed)
        sent.append(sealed)
    counters = _stored_counters(store)
    assert len(counters) <= 3 * table + 1, sorted(counters)
    assert "epoch:announcement:floor" in counters
    for sealed in sent[:-table]:  # every forgotten prefix: refused, never accepted again
        with pytest.raises(MessageStaleError):
            verifier.open(sealed)
    verifier.close()
    store.close()
    reopened = sqlite_store(tmp_path / "verifier.db", clock=clock)
    restarted = EpochVerifier(PSK, store=reopened, clock=clock, max_prefixes=table)
    for sealed in sent:
        with pytest.raises(ReplayAttackError):
            restarted.open(sealed)
    assert _stored_counters(reopened).keys() == counters.keys()
    reopened.close()


def test_forget_persists_the_floor_before_the_table_moves(
    tmp_path: Path, clock: ManualClock
) -> None:
    """Persist, then believe: a failed forget leaves the table holding the old prefix (a
    real store whose forget fails, not a patched one: the memory store is compiled)."""
    store = started_before(clock, lambda: _FlakySqlite(tmp_path / "verifier.db", clock=clock))
    verifier = EpochVerifier(PSK, store=store, clock=clock, max_prefixes=1)
    first, second = EpochSigner(PSK, clock=clock), EpochSigner(PSK, clock=clock)
    held = verifier.open(first.seal(b"a")).nonce_prefix
    clock.advance(1)
    store.forget_down = True
    with pytest.raises(StateUnavailableError):
        verifier.open(second.seal(b"b"))
    assert verifier.last(held) is not None
    store.close()


@pytest.mark.parametrize("backend", ["sqlite", "redis"])
def test_a_prefix_forgotten_by_one_verifier_stays_refused_by_another(
    backend: str, tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    """Two verifiers on one store, tables of two: A accepts P1's capture, then P2 and P3
    (evicting P1: its counter is deleted under the raised floor).  B, which never held
    P1, refuses the capture before and after A forgot it (it reads the counter, then the
    floor), and so does a restarted B."""
    clock = ManualClock(wall=2_000_000_000.0)
    prefix = f"t-{uuid.uuid4().hex}:"

    def store() -> SqliteStore | RedisStore:
        if backend == "sqlite":
            return sqlite_store(tmp_path / "shared.db", clock=clock)
        return RedisStore(request.getfixturevalue("redis_url"), prefix=prefix, clock=clock)

    a = EpochVerifier(PSK, store=store(), clock=clock, max_prefixes=2)
    b = EpochVerifier(PSK, store=store(), clock=clock, max_prefixes=2)
    clock.step_wall(200)  # past any start fence
    s1, s2, s3 = (EpochSigner(PSK, nonce_prefix=bytes([i]) * 8, clock=clock) for i in (1, 2, 3))
    capture = s1.seal(b"P1 announcement")
    a.open(capture)
    clock.step_wall(0.1)
    a.open(s2.seal(b"p2"))
    with pytest.raises(ReplayAttackError):
        b.open(capture)
    clock.step_wall(0.1)
    a.open(s3.seal(b"p3"))  # evicts P1: forget
    assert a.store.current("epoch:announcement:" + (b"\x01" * 8).hex()) is None
    with pytest.raises(ReplayAttackError):
        b.open(capture)
    with pytest.raises(ReplayAttackError):
        EpochVerifier(PSK, store=store(), clock=clock, max_prefixes=2).open(capture)


def test_fleet_key_rotation_overlaps_until_the_cutover_then_retires_the_old_key() -> None:
    """``KeyRotation`` on a manual clock: writers keep the old key until the cut-over and
    seal with the new one after it; readers accept both until the cut-over; after it, a
    frame the old key sealed is refused with its own reason (authentic, ``key_retired``)
    and one the new key sealed passes."""
    from antireplay.epochs import KeyRotation  # noqa: PLC0415
    from antireplay.epochs.policy import KEY_RETIRED  # noqa: PLC0415
    from antireplay.epochs.sealing import refused  # noqa: PLC0415

    old, new = b"o" * 32, b"n" * 32
    clock = ManualClock(wall=1_000.0)
    rotation = KeyRotation(new, cutover_ns=int(1_010 * 1e9))
    verifier = started_before(clock, lambda: EpochVerifier(
        old, clock=clock, max_age_s=30, max_forward_s=5, rotation=rotation))  # fmt: skip
    plain = started_before(clock, lambda: EpochVerifier(old, clock=clock, max_forward_s=5))
    rotating = EpochSigner(old, clock=clock, rotation=rotation)
    old_only = EpochSigner(old, clock=clock)  # a writer that never got the new key
    new_only = EpochSigner(new, clock=clock)  # one configured with the new key early

    def opens(sealed: bytes) -> bool:
        return verifier.open(sealed).epoch > 0

    before = rotating.seal(b"before")
    assert opens(before) and opens(old_only.seal(b"old key, before")) and opens(
        new_only.seal(b"new key, before"))  # fmt: skip
    assert plain.open(rotating.seal(b"sealed with the old key")).epoch > 0
    clock.advance(11)  # past the cut-over
    after = rotating.seal(b"after")
    with pytest.raises(SignatureInvalidError):  # sealed with the new key now
        plain.open(after)
    assert opens(after) and opens(new_only.seal(b"new key, after"))
    stolen = old_only.seal(b"old key, after the cut-over")
    with pytest.raises(SignatureInvalidError) as retired:
        verifier.open(stolen)
    assert retired.value.detail == KEY_RETIRED and "retired fleet key" in retired.value.reason
    verdict = refused(retired.value, "", stolen)
    assert (verdict.outcome, verdict.code, verdict.authentic) == (
        KEY_RETIRED,
        Code.SIGNATURE_INVALID,
        True,
    )
    with pytest.raises(SignatureInvalidError, match="does not verify"):  # a third key: forged
        verifier.open(EpochSigner(b"x" * 32, clock=clock).seal(b"forged"))
