"""The command line: demo, config check, state repair."""

from __future__ import annotations

from pathlib import Path

import pytest
from benchmarks.__main__ import MODULES
from click.testing import CliRunner

from antireplay.cli import main
from antireplay.counters import NonceCounter
from antireplay.demo import GatewayProcess, write_demo_config
from antireplay.errors import StateFileError
from tests.conftest import ROOT


@pytest.mark.parametrize("args", [["demo", "--in-process"], ["demo"]])
def test_demo_passes(args: list[str]) -> None:
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "behaved as expected" in result.output
    assert "MISMATCH" not in result.output


def test_keygen_sign_send_and_audit(tmp_path: Path) -> None:
    runner = CliRunner()
    gw = GatewayProcess(write_demo_config(tmp_path))
    gw.start()
    try:
        signed = runner.invoke(
            main,
            ["sign", "--key", str(tmp_path / "operator.key.pem"), "--kid", "operator",
             "--cmd", "move_forward", "--target", "rcan://r/acme/arm/v2/u1", "--param", "d=1.5"],
        )  # fmt: skip
        assert signed.exit_code == 0, signed.output
        envelope = tmp_path / "msg.json"
        envelope.write_text(signed.output)
        sent = runner.invoke(main, ["send", gw.url, str(envelope)])
        assert sent.exit_code == 0, sent.output
        again = runner.invoke(main, ["send", gw.url, str(envelope)])
        assert again.exit_code == 1 and "REPLAY_DETECTED" in again.output
    finally:
        gw.stop()
    checked = runner.invoke(main, ["audit", "verify", str(tmp_path / "audit.db")])
    assert checked.exit_code == 0 and "2 records" in checked.output
    tail = runner.invoke(main, ["audit", "tail", str(tmp_path / "audit.db")])
    assert "rejected" in tail.output and tail.exit_code == 0
    made = runner.invoke(main, ["keygen", "--alg", "ml-dsa-87", "--out", str(tmp_path / "k")])
    assert made.exit_code == 0 and (tmp_path / "k.pub.pem").exists()
    again_made = runner.invoke(main, ["keygen", "--out", str(tmp_path / "k")])
    assert again_made.exit_code == 2


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
    counter.close()
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


def test_bench_refuses_unknown_names_and_lists_the_benchmarks(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(ROOT)
    result = CliRunner().invoke(main, ["bench", "no_such"])
    assert result.exit_code == 2
    assert "unknown benchmark no_such" in result.output
    for name in MODULES:  # the CLI and `python -m benchmarks` find the same modules
        assert name in result.output.replace("\n", "")


def test_bench_outside_a_checkout_says_so(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(main, ["bench"])
    assert result.exit_code == 2
    assert "source checkout" in result.output
