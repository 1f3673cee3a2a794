"""The command line: demo, config check, state repair."""

from __future__ import annotations

from pathlib import Path

from click.testing import CliRunner

from antireplay.cli import main
from antireplay.counters import NonceCounter
from antireplay.errors import StateFileError


def test_demo_passes() -> None:
    result = CliRunner().invoke(main, ["demo"])
    assert result.exit_code == 0, result.output
    assert "behaved as expected" in result.output
    assert "MISMATCH" not in result.output


def test_config_check_reports_key_value_range(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("security:\n  replay_window_s: 1000\n")
    result = CliRunner().invoke(main, ["config", "check", str(bad)])
    assert result.exit_code == 2
    assert "security.replay_window_s=1000" in result.output
    assert "5 to 300" in result.output
    good = tmp_path / "good.yaml"
    good.write_text("security:\n  replay_window_s: 60\n")
    assert CliRunner().invoke(main, ["config", "check", str(good)]).exit_code == 0


def test_state_repair_reseeds_a_corrupt_counter(tmp_path: Path) -> None:
    path = tmp_path / "c.state"
    counter = NonceCounter.persistent(path, lease=4)
    used = [counter.next() for _ in range(9)]
    raw = path.read_bytes()
    path.write_bytes(raw.replace(b'"ceiling":12', b'"ceiling":13'))
    try:
        NonceCounter.persistent(path)
        raise AssertionError("a corrupt file must refuse to start")
    except StateFileError as exc:
        assert "antireplay state repair" in str(exc)
    result = CliRunner().invoke(main, ["state", "repair", str(path)])
    assert result.exit_code == 0, result.output
    assert NonceCounter.persistent(path).next() > max(used)


def test_state_repair_needs_kind_for_unreadable_file(tmp_path: Path) -> None:
    path = tmp_path / "x.state"
    path.write_bytes(b"\0\0\0")
    assert CliRunner().invoke(main, ["state", "repair", str(path)]).exit_code == 2
    result = CliRunner().invoke(main, ["state", "repair", str(path), "--kind", "epoch-verifier"])
    assert result.exit_code == 0, result.output
