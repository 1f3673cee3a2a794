"""The crash-safe state writer: checksums, generations, rollback witness, refusal, repair."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from click.testing import CliRunner

from antireplay.cli import main
from antireplay.core.errors import StateFileError
from antireplay.epochs import EpochSigner, signer_state
from antireplay.state.ceilings import persistent_counter
from antireplay.state.durable import DurableState, repair
from harness import ROOT


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
    counter = persistent_counter(path, lease=10)
    used = [counter.next() for _ in range(25)]
    counter.close()
    path.write_bytes(path.read_bytes()[:10])
    with pytest.raises(StateFileError, match="corrupt or truncated"):
        persistent_counter(path)
    reseeded = repair(path, "nonce-counter", now_ns=5_000)
    assert reseeded == {"ceiling": 5_000}
    resumed = persistent_counter(path)
    assert resumed.next() > max(used)


def test_repair_keeps_salvaged_ceiling_when_above_clock(tmp_path: Path) -> None:
    path = tmp_path / "ctr.state"
    counter = persistent_counter(path, lease=1_000)
    counter.next()
    counter.close()
    path.with_name(path.name + ".gen").unlink()
    assert repair(path, "nonce-counter", now_ns=10) == {"ceiling": 1_000}
    assert persistent_counter(path).next() == 1_001


def test_repair_of_unknown_kind_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(StateFileError, match="unknown state kind"):
        repair(tmp_path / "x", "nope")


# --- wrong-typed content behind a valid checksum ------------------------------------------------


def forge(path: Path, kind: str, data: dict[str, object]) -> None:
    """A state file whose checksum and witness are valid but whose data has the wrong shape."""
    state = DurableState(path, kind=kind)
    state.save(data)


@pytest.mark.parametrize(
    ("kind", "data"),
    [
        ("nonce-counter", {"ceiling": "12"}),
        ("nonce-counter", {"ceiling": True}),
        ("nonce-counter", {"ceiling": -4}),
        ("nonce-counter", {}),
        ("epoch-signer", {"ceiling": 5, "prefix": "zz" * 8}),
        ("epoch-signer", {"ceiling": 5, "prefix": 7}),
        ("epoch-signer", {"ceiling": [], "prefix": "00" * 8}),
        ("epoch-signer", {"ceiling": 5, "prefix": "00" * 8, "rotations": "1"}),
    ],
)
def test_wrong_typed_content_is_refused_naming_file_and_repair(
    tmp_path: Path, kind: str, data: dict[str, object]
) -> None:
    path = tmp_path / "x.state"
    forge(path, kind, data)
    owners: dict[str, Callable[[], object]] = {
        "nonce-counter": lambda: persistent_counter(path),
        "epoch-signer": lambda: EpochSigner(b"k" * 32, state=signer_state(path)),
    }
    with pytest.raises(StateFileError) as err:
        owners[kind]()
    message = str(err.value)
    assert "invalid content" in message
    assert str(path) in message and f"antireplay state repair {path}" in message
    repair(path, kind, now_ns=1_000)  # the refused owner gave its lock back
    owners[kind]()


# --- one owner per file -------------------------------------------------------------------------


def hold(path: Path, kind: str) -> subprocess.Popen[str]:
    """A real second process that opens the state file as its owner and waits on stdin."""
    code = (
        "import sys; from antireplay.state.ceilings import persistent_counter; "
        "from antireplay.epochs import EpochSigner, signer_state; p = sys.argv[1]; "
        "o = persistent_counter(p) if sys.argv[2] == 'nonce-counter' "
        "else EpochSigner(b'k' * 32, state=signer_state(p)); "
        "print(o.next() if sys.argv[2] == 'nonce-counter' else o.next_epoch(), flush=True); "
        "sys.stdin.read()"
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(path), kind],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    assert proc.stdout is not None
    if not proc.stdout.readline():
        assert proc.stderr is not None
        pytest.fail(f"the owner process did not start: {proc.stderr.read()}")
    return proc


@pytest.mark.parametrize("kind", ["nonce-counter", "epoch-signer"])
def test_second_process_on_one_state_file_is_refused(tmp_path: Path, kind: str) -> None:
    path = tmp_path / "shared.state"
    first = hold(path, kind)
    try:
        probe = subprocess.run(
            [sys.executable, "-c", (
                "import sys; from antireplay.state.ceilings import persistent_counter; "
                "from antireplay.epochs import EpochSigner, signer_state; p = sys.argv[1]; "
                "persistent_counter(p) if sys.argv[2] == 'nonce-counter' "
                "else EpochSigner(b'k' * 32, state=signer_state(p))"
            ), str(path), kind],
            capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(ROOT / "src")),
            timeout=60, check=False,
        )  # fmt: skip
        assert probe.returncode != 0
        assert "StateFileError" in probe.stderr and "in use by another owner" in probe.stderr
        assert str(path) in probe.stderr
        with pytest.raises(StateFileError, match="in use"):  # nor in this process
            repair(path, kind)
        refused = CliRunner().invoke(main, ["state", "repair", str(path)])
        assert refused.exit_code == 2  # no reseed under a live owner
        assert "in use by another owner" in " ".join(refused.output.split())
    finally:
        first.communicate("", timeout=30)  # the owner exits; the kernel drops its lock
    assert first.returncode == 0
    second = hold(path, kind)  # now the file can be owned again
    second.communicate("", timeout=30)


def test_second_owner_in_one_process_is_refused_until_closed(tmp_path: Path) -> None:
    path = tmp_path / "c.state"
    first = persistent_counter(path, lease=4)
    first.next()
    with pytest.raises(StateFileError, match="in use by another owner"):
        persistent_counter(path)
    first.close()
    assert persistent_counter(path).next() == 5
