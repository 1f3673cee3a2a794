"""The epoch verifier on a SQLite store: a durable write is reported as durable (a witness
that cannot be written after COMMIT fails no epoch, and is surfaced on its own), and a
store with no history fences the verifier's start as a memory store does."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from antireplay import ManualClock
from antireplay.core.errors import EpochReplayedError, MessageStaleError, StateUnavailableError
from antireplay.epochs import EpochSigner, EpochVerifier
from antireplay.state.sqlite import SqliteStore
from harness import started_before
from harness.stores import sqlite_store

PSK = b"fleet-pre-shared-key-0123456789ab"


def _witness_fails(store: SqliteStore, monkeypatch: pytest.MonkeyPatch) -> None:
    def write(*_: object, **__: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(store.witness, "write", write)


def test_a_witness_failure_after_commit_accepts_the_epoch_once(
    tmp_path: Path, clock: ManualClock, monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:  # fmt: skip
    store = sqlite_store(tmp_path / "verifier.db", clock=clock)
    signer = EpochSigner(PSK, clock=clock)
    verifier = started_before(clock, lambda: EpochVerifier(PSK, store=store, clock=clock))
    _witness_fails(store, monkeypatch)
    sealed = signer.seal(b"first")
    with caplog.at_level(logging.ERROR, logger="antireplay.state.sqlite"):
        got = verifier.open(sealed)  # durable: accepted, not STATE_UNAVAILABLE
        assert got.payload == b"first" and verifier.last(signer.nonce_prefix) == got.epoch
        with pytest.raises(EpochReplayedError):  # its redelivery is a replay, rightly
            verifier.open(sealed)
        clock.advance(0.001)
        assert verifier.open(signer.seal(b"second")).payload == b"second"
    errors = [r.message for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "witness" in errors[0]  # logged once
    assert store.status()["witness_failures"] >= 2  # counted every time, logged once
    with pytest.raises(StateUnavailableError, match="witness"):
        store.ready()  # readiness says so, on its own
    monkeypatch.undo()
    store.ready()  # the probe writes the witness again: ready
    store.close()
    reopened = SqliteStore(tmp_path / "verifier.db", clock=clock)
    assert reopened.loss_reason is None  # the witness caught up: no false alarm
    reopened.close()


def test_a_witness_failure_is_no_failed_commit(
    tmp_path: Path, clock: ManualClock, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = sqlite_store(tmp_path / "state.db", clock=clock)
    _witness_fails(store, monkeypatch)
    seen = store.commit("a", clock.wall() + 30, clock.wall())
    assert seen.recorded
    assert not store.commit("a", clock.wall() + 30, clock.wall()).recorded  # it is durable
    assert store.advance("counter", 5) and store.current("counter") == 5
    store.close()


def test_a_verifier_on_a_new_sqlite_store_fences_like_a_memory_one(
    tmp_path: Path, clock: ManualClock
) -> None:
    """A reader on a state with no history fences ``max_forward_s`` from its start, as on
    a memory store; a challenge answered by the sender opens it at once."""
    signer = EpochSigner(PSK, clock=clock)
    captured = signer.seal(b"sealed before the reader's state began")
    store = SqliteStore(tmp_path / "reader.db", clock=clock)
    verifier = EpochVerifier(PSK, store=store, clock=clock, max_forward_s=5)
    on_memory = EpochVerifier(PSK, clock=clock, max_forward_s=5)
    assert verifier.restart_fence() == on_memory.restart_fence() and verifier.fenced()
    with pytest.raises(MessageStaleError) as refused:
        verifier.open(captured)
    assert refused.value.detail == "restart_fence"
    challenge = verifier.challenge()
    assert challenge is not None
    verifier.open_answer(signer.answer(challenge))
    clock.advance(0.001)
    assert verifier.open(signer.seal(b"fresh, above the answer")).payload.startswith(b"fresh")
    store.close()
