"""The crash-safe state writer: checksums, generations, rollback witness, refusal, repair."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from antireplay.counters import NonceCounter
from antireplay.durable import DurableState, repair
from antireplay.errors import StateFileError


def make(tmp_path: Path, gens: int = 1) -> DurableState:
    state = DurableState(tmp_path / "s.state", kind="nonce-counter")
    for g in range(gens):
        state.save({"ceiling": (g + 1) * 100})
    return state


def test_round_trip_and_fresh_start(tmp_path: Path) -> None:
    fresh = DurableState(tmp_path / "none.state", kind="nonce-counter")
    assert fresh.load() is None
    make(tmp_path, gens=3)
    again = DurableState(tmp_path / "s.state", kind="nonce-counter")
    assert again.load() == {"ceiling": 300}
    assert again.generation == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.state", "s.state.gen"]


@pytest.mark.parametrize(
    ("damage", "problem"),
    [
        (lambda b: b[: len(b) // 2], "corrupt or truncated"),
        (lambda b: b"", "corrupt or truncated"),
        (lambda b: b.replace(b'"ceiling":300', b'"ceiling":999'), "checksum mismatch"),
        (lambda b: bytes([b[0] ^ 0x01]) + b[1:], "corrupt or truncated"),
        (lambda b: b'{"format": "something-else"}', "not an antireplay state file"),
    ],
)
def test_damaged_file_refuses_start_naming_file_and_repair(
    tmp_path: Path, damage: object, problem: str
) -> None:
    make(tmp_path, gens=3)
    path = tmp_path / "s.state"
    path.write_bytes(damage(path.read_bytes()))  # type: ignore[operator]
    with pytest.raises(StateFileError) as err:
        DurableState(path, kind="nonce-counter").load()
    assert problem in str(err.value)
    assert str(path) in str(err.value)
    assert f"antireplay state repair {path}" in str(err.value)


def test_rolled_back_file_is_refused(tmp_path: Path) -> None:
    state = make(tmp_path, gens=2)
    shutil.copy(state.path, tmp_path / "backup")
    state.save({"ceiling": 300})
    state.save({"ceiling": 400})
    shutil.copy(tmp_path / "backup", state.path)  # restore an old backup of the main file
    with pytest.raises(StateFileError, match="rolled back"):
        DurableState(state.path, kind="nonce-counter").load()


def test_crash_between_main_and_witness_is_accepted(tmp_path: Path) -> None:
    state = make(tmp_path, gens=2)
    shutil.copy(state.witness, tmp_path / "old-witness")
    state.save({"ceiling": 300})
    shutil.copy(tmp_path / "old-witness", state.witness)  # witness one generation behind
    assert DurableState(state.path, kind="nonce-counter").load() == {"ceiling": 300}


def test_missing_witness_or_main_is_refused(tmp_path: Path) -> None:
    state = make(tmp_path, gens=2)
    state.witness.unlink()
    with pytest.raises(StateFileError, match="witness missing"):
        DurableState(state.path, kind="nonce-counter").load()
    (tmp_path / "x").mkdir()
    other = make(tmp_path / "x", gens=1)
    other.path.unlink()
    with pytest.raises(StateFileError, match="missing while its witness exists"):
        DurableState(other.path, kind="nonce-counter").load()


def test_wrong_kind_is_refused(tmp_path: Path) -> None:
    state = make(tmp_path)
    with pytest.raises(StateFileError, match="not 'epoch-signer'"):
        DurableState(state.path, kind="epoch-signer").load()


def test_persistent_counter_refuses_corrupt_file_then_repair_reseeds_above(tmp_path: Path) -> None:
    path = tmp_path / "ctr.state"
    counter = NonceCounter.persistent(path, lease=10)
    used = [counter.next() for _ in range(25)]
    path.write_bytes(path.read_bytes()[:10])
    with pytest.raises(StateFileError):
        NonceCounter.persistent(path)
    reseeded = repair(path, "nonce-counter", now_ns=5_000)
    assert reseeded == {"ceiling": 5_000}
    resumed = NonceCounter.persistent(path)
    assert resumed.next() > max(used)


def test_repair_keeps_salvaged_ceiling_when_above_clock(tmp_path: Path) -> None:
    path = tmp_path / "ctr.state"
    counter = NonceCounter.persistent(path, lease=1_000)
    counter.next()
    path.with_name(path.name + ".gen").unlink()
    assert repair(path, "nonce-counter", now_ns=10) == {"ceiling": 1_000}
    assert NonceCounter.persistent(path).next() == 1_001


def test_repair_of_unknown_kind_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown state kind"):
        repair(tmp_path / "x", "nope")
