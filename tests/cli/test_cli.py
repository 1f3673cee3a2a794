"""The command line: demo, config check, state repair."""

from __future__ import annotations

import json
import socket
import sqlite3
import subprocess
import sys
from pathlib import Path
from typing import Any

import click
import pytest
import yaml
from click.testing import CliRunner
from cryptography.hazmat.primitives.asymmetric import ed25519
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from antireplay.audit import AuditLog, AuditRow
from antireplay.cli import main
from antireplay.cli.demo import write_demo_config
from antireplay.core.errors import StateFileError
from antireplay.mavlink import passphrase_key
from antireplay.mavlink.sim import SimVehicle
from antireplay.rcan.auth import SDK_PRIVATE_MAGIC, write_key_pair
from antireplay.state.ceilings import persistent_counter
from antireplay.wiring.mavlink import (
    Allowed,
    allowed_messages,
    link_key,
    read_signing_keys,
)
from harness import ROOT, GatewayProcess, one_line_error
from harness.stores import aged_state

ROBOT = "rcan://registry.rcan.dev/acme/arm/v2/unit-001"


@pytest.mark.parametrize("args", [["demo", "--in-process"], ["demo"]])
def test_demo_passes(args: list[str]) -> None:
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "behaved as expected" in result.output
    assert "MISMATCH" not in result.output


def test_keygen_sign_send_and_audit(tmp_path: Path) -> None:
    runner = CliRunner()
    gw = GatewayProcess(write_demo_config(tmp_path))
    aged_state(tmp_path / "state.db")  # a deployment started earlier: no first-start row
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


def test_config_check_speaks_of_keys_and_files_not_pydantic(tmp_path: Path) -> None:
    run = CliRunner().invoke
    top = tmp_path / "top.yaml"
    top.write_text("replay_window_s: 30\n")
    line = one_line_error(run(main, ["config", "check", str(top)]))
    assert line == "antireplay: error: replay_window_s: " + (
        "not a top-level key; it belongs under security:"
    )
    missing = tmp_path / "missing-key.yaml"
    missing.write_text("keys: [{kid: a, owner: o, alg: ed25519, public_keys: [gone.pem]}]\n")
    line = one_line_error(run(main, ["config", "check", str(missing)]))
    assert line == "antireplay: error: keys.a.public_keys: file not found: gone.pem"


def test_config_check_is_a_short_verdict_and_verbose_shows_the_rest(tmp_path: Path) -> None:
    write_demo_config(tmp_path)
    path = str(tmp_path / "antireplay.yaml")
    short = CliRunner().invoke(main, ["config", "check", path])
    assert short.exit_code == 0, short.output
    assert short.stdout.splitlines() == [
        f"ok: 1 keys, store sqlite:{tmp_path}/state.db, audit {tmp_path}/audit.db"
    ]
    verbose = CliRunner().invoke(main, ["config", "check", "--verbose", path])
    assert '"replay_window_s": 30.0' in verbose.stdout
    assert verbose.stdout.splitlines()[-1] == short.stdout.splitlines()[0]


def test_config_check_probes_an_http_upstream(tmp_path: Path) -> None:
    closed = socket.socket()
    closed.bind(("127.0.0.1", 0))
    port = closed.getsockname()[1]  # bound, never listening: a connection is refused
    path = tmp_path / "up.yaml"
    path.write_text(f"upstream: http://127.0.0.1:{port}/robot\n")
    try:
        line = one_line_error(CliRunner().invoke(main, ["config", "check", str(path)]))
        assert line.startswith(f"antireplay: error: upstream http://127.0.0.1:{port}/robot: ")
        assert "refused" in line
        closed.listen()
        alive = CliRunner().invoke(main, ["config", "check", str(path)])
        assert alive.exit_code == 0, alive.output
    finally:
        closed.close()


def test_state_repair_reseeds_a_corrupt_counter(tmp_path: Path) -> None:
    path = tmp_path / "c.state"
    counter = persistent_counter(path, lease=4)
    used = [counter.next() for _ in range(9)]
    counter.close()
    raw = path.read_bytes()
    path.write_bytes(raw.replace(b'"ceiling":12', b'"ceiling":13'))
    try:
        persistent_counter(path)
        raise AssertionError("a corrupt file must refuse to start")
    except StateFileError as exc:
        assert "antireplay state repair" in str(exc)
    result = CliRunner().invoke(main, ["state", "repair", str(path)])
    assert result.exit_code == 0, result.output
    assert persistent_counter(path).next() > max(used)


def test_state_repair_needs_kind_for_unreadable_file(tmp_path: Path) -> None:
    path = tmp_path / "x.state"
    path.write_bytes(b"\0\0\0")
    assert CliRunner().invoke(main, ["state", "repair", str(path)]).exit_code == 2
    result = CliRunner().invoke(main, ["state", "repair", str(path), "--kind", "epoch-signer"])
    assert result.exit_code == 0, result.output


def test_bench_refuses_unknown_names_and_lists_the_benchmarks(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(ROOT)
    result = CliRunner().invoke(main, ["bench", "no_such"])
    assert result.exit_code == 2
    assert "unknown benchmark no_such" in result.output
    listed = subprocess.run(
        [sys.executable, "-m", "benchmarks", "no_such"],
        check=False, cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert listed.returncode == 1 and "unknown benchmark bench_no_such" in listed.stderr
    modules = listed.stderr.split("choose from ")[1].strip().split(", ")
    assert "bench_window" in modules
    for name in modules:  # the CLI and `python -m benchmarks` find the same modules
        assert name in result.output.replace("\n", "")


def test_bench_outside_a_checkout_says_so(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(main, ["bench"])
    assert result.exit_code == 2
    assert "source checkout" in result.output


# --- ordinary mistakes: one line on stderr, exit 2, no traceback ---------------------------------


def garbage(path: Path) -> Path:
    path.write_bytes(b"this is not an SQLite database at all\n" * 40)
    return path


def table_names(path: Path) -> list[str]:
    db = sqlite3.connect(path)
    try:
        return [row[0] for row in db.execute("SELECT name FROM sqlite_master")]
    finally:
        db.close()


def test_serve_bad_inputs(tmp_path: Path) -> None:
    run = CliRunner().invoke
    one_line_error(run(main, ["serve", "--port", "70000"]), "--port", "70000", "0<=x<=65535")
    one_line_error(run(main, ["serve", "--port", "http"]), "--port", "http")
    state = tmp_path / "state"
    state.mkdir()
    garbage(state / "audit.db")
    line = one_line_error(run(main, ["serve", "--state-dir", str(state)]), "audit.db")
    assert len(line) > 80  # long, and still one line: never hard-wrapped


def test_sign_bad_inputs(tmp_path: Path) -> None:
    run = CliRunner().invoke
    base = ["sign", "--kid", "op", "--cmd", "c", "--target", ROBOT]
    one_line_error(run(main, [*base, "--key", str(tmp_path / "missing.pem")]), "--key", "missing")
    not_pem = tmp_path / "not.pem"
    not_pem.write_text("hello")
    one_line_error(run(main, [*base, "--key", str(not_pem)]), "--key", "not.pem", "PEM")
    write_key_pair(ed25519.Ed25519PrivateKey.generate(), tmp_path / "k.pem", tmp_path / "p.pem")
    bad_json = tmp_path / "m.json"
    bad_json.write_text("{not json")
    args = [*base, "--key", str(tmp_path / "k.pem"), "--json", str(bad_json)]
    one_line_error(run(main, args), "--json", "m.json", "not JSON")
    bad_json.write_text("[1, 2]")
    one_line_error(run(main, args), "--json", "JSON object")
    no_kid = ["sign", "--key", str(tmp_path / "k.pem"), "--cmd", "c", "--target", ROBOT]
    one_line_error(run(main, no_kid), "--kid", "--sdk")
    sdk = [*no_kid, "--sdk"]
    one_line_error(run(main, sdk), "--key", "k.pem", "ML-DSA-65")
    one_line_error(run(main, [*sdk, "--key", str(tmp_path / "k.pem")]), "exactly one --key")


def test_sign_refuses_what_it_would_mislabel(tmp_path: Path) -> None:
    """A key of another algorithm than --alg, an SDK key file without --sdk, a target that
    is no robot URI, a qos outside 0..2: one line each, nothing signed."""
    run = CliRunner().invoke
    write_key_pair(ed25519.Ed25519PrivateKey.generate(), tmp_path / "k.pem", tmp_path / "p.pem")
    base = ["sign", "--key", str(tmp_path / "k.pem"), "--kid", "op", "--cmd", "c"]
    line = one_line_error(run(main, [*base, "--alg", "ml-dsa-65", "--target", ROBOT]))
    assert line == (
        "antireplay: error: --alg ml-dsa-65: the --key given is ed25519; give --alg matching "
        "the key"
    )
    one_line_error(run(main, [*base, "--alg", "rsa"]), "--alg", "'ed25519', 'ed25519+ml-dsa-65'")
    one_line_error(run(main, [*base, "--target", "robot-7"]), "--target robot-7", "rcan://")
    one_line_error(run(main, [*base, "--qos", "3"]), "--qos", "0<=x<=2")
    sdk_file = tmp_path / "sdk.key"
    sdk_file.write_bytes(SDK_PRIVATE_MAGIC + bytes(64))
    line = one_line_error(run(main, ["sign", "--key", str(sdk_file), "--kid", "op"]))
    assert (
        line
        == f"antireplay: error: --key {sdk_file}: an RCAN SDK key file; sign with it using --sdk"
    )
    signed = run(main, [*base, "--qos", "1", "--target", ROBOT])
    assert signed.exit_code == 0 and json.loads(signed.stdout)["qos"] == 1


def test_mavlink_proxy_bad_inputs(tmp_path: Path) -> None:
    """Every case listens on a busy port, so none can hang serving if its check broke."""
    run = CliRunner().invoke
    key = tmp_path / "link.key"
    key.write_bytes(bytes(range(32)))
    key.chmod(0o600)  # a secret (a wider one is warned about)
    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("127.0.0.1", 0))
    port = busy.getsockname()[1]
    base = ["mavlink-proxy", "--forward", "udp:127.0.0.1:9", "--key-file", str(key),
            "--audit", str(tmp_path / "audit.db"), "--store", "memory",
            "--listen", f"udp:127.0.0.1:{port}"]  # fmt: skip
    try:
        one_line_error(run(main, [*base, "--store", "bogus:x"]), "--store", "bogus:x")
        foreign = garbage(tmp_path / "foreign-audit.db")
        line = one_line_error(run(main, [*base, "--audit", str(foreign)]), "foreign-audit.db")
        assert "not an antireplay audit trail" in line
        one_line_error(run(main, [*base, "--forward", "udp:127.0.0.1:70000"]), "70000", "0..65535")
        one_line_error(run(main, [*base, "--forward", "tcp:x"]), "tcp:x", "udp:HOST:PORT")
        line = one_line_error(run(main, base), str(port))
        assert "in use" in line
    finally:
        busy.close()


def test_mavlink_router_key_and_allow_list_options(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Per-link passphrases in MAVProxy's signing.keys format, the default key from an
    environment variable, per-direction allow-lists; mistakes are one line naming them."""
    keys = tmp_path / "signing.keys"
    keys.write_text("udpin:0.0.0.0:14550 ground-pass\n127.0.0.1:14560 radio-pass\nbad line here\n")
    found = read_signing_keys(keys)
    assert link_key("udpin:0.0.0.0:14550", found, None) == passphrase_key("ground-pass")
    assert link_key("udpout:127.0.0.1:14560", found, None) == passphrase_key("radio-pass")
    assert link_key("/dev/ttyACM0,57600", found, b"d" * 32) == b"d" * 32
    to_vehicle, from_vehicle = allowed_messages(
        ("RADIO_STATUS:v1", "to-vehicle:0", "from-vehicle:166")
    )
    assert to_vehicle == Allowed(frozenset({109, 0}), frozenset({109}))
    assert from_vehicle == Allowed(frozenset({109, 166}), frozenset({109}))
    run = CliRunner().invoke
    base = ["mavlink-router", "--audit", str(tmp_path / "audit.db"), "--store", "memory"]
    one_line_error(run(main, [*base, "--ground", "udpin:127.0.0.1:0"]), "--vehicle")
    vehicle = [*base, "--vehicle", "/dev/ttyACM0,57600"]
    one_line_error(run(main, vehicle), "/dev/ttyACM0,57600", "no key")
    monkeypatch.delenv("MAV_PASS", raising=False)
    one_line_error(run(main, [*vehicle, "--passphrase-env", "MAV_PASS"]), "MAV_PASS")
    monkeypatch.setenv("MAV_PASS", "pass")
    keyed = [*vehicle, "--passphrase-env", "MAV_PASS"]
    one_line_error(run(main, [*keyed, "--allow-unsigned", "NOPE"]), "NOPE", "RADIO_STATUS")
    one_line_error(run(main, [*keyed, "--vehicle", "serial0"]), "serial0")
    one_line_error(run(main, [*keyed, "--max-forward-s", "0"]), "--max-forward-s")
    one_line_error(run(main, [*base, "--vehicle", "/dev/null,115200", "--passphrase-env",
                              "MAV_PASS"]), "/dev/null,115200", "not a serial port")  # fmt: skip
    missing = str(tmp_path / "no-such-tty")
    one_line_error(run(main, ["mavlink-router", "--audit", str(tmp_path / "audit.db"), "--store",
                              "memory", "--vehicle", f"{missing},57600", "--passphrase-env",
                              "MAV_PASS"]), missing)  # fmt: skip


@pytest.mark.parametrize("command", ["tail", "verify"])
def test_audit_commands_refuse_files_that_are_not_audit_trails(
    tmp_path: Path, command: str
) -> None:
    run = CliRunner().invoke
    junk = garbage(tmp_path / "junk.db")
    one_line_error(run(main, ["audit", command, str(junk)]), "junk.db", "not an SQLite database")
    other = tmp_path / "other.db"
    db = sqlite3.connect(other)
    db.execute("CREATE TABLE notes (x)")
    db.commit()
    db.close()
    one_line_error(run(main, ["audit", command, str(other)]), "other.db", "without an audit table")
    assert table_names(other) == ["notes"]  # nothing was created in someone else's file
    one_line_error(run(main, ["audit", command, str(tmp_path / "none.db")]), "none.db")


def headless(path: Path) -> Path:
    """An audit trail with rows whose head checkpoint was deleted."""
    log = AuditLog(path)
    log.append(AuditRow(
        at=1_800_000_000.0, outcome="accepted", code=None, warning=None, msg_type=1,
        sender="op", sender_verified=True, msg_id="m1",
    ))  # fmt: skip
    log.close()
    path.with_name(path.name + ".head").unlink()
    return path


def test_config_check_runs_every_check_serve_runs(tmp_path: Path) -> None:
    """Each configuration ``serve`` refuses, ``config check`` refuses with the same line."""
    run = CliRunner().invoke
    state = tmp_path / "s"
    state.mkdir()
    write_demo_config(state)
    good = yaml.safe_load((state / "antireplay.yaml").read_text())
    bad_cases: dict[str, tuple[dict[str, Any], str]] = {
        "missing key file": ({"keys": [{**good["keys"][0], "public_keys": ["gone.pem"]}]},
                             "gone.pem"),
        "unknown store": ({"store": "bogus:x"}, "bogus:x"),
        "unopenable store": ({"store": f"sqlite:{garbage(tmp_path / 'st.db')}"}, "st.db"),
        "unimportable upstream": ({"upstream": "no_such_module_x:robot"}, "no_such_module_x"),
        "foreign audit file": ({"audit": str(garbage(tmp_path / 'a.db'))}, "a.db"),
        "missing jwt key": ({"jwt": {"keys": {"j": "gone-jwt.pem"}}}, "gone-jwt.pem"),
        "trail without its head checkpoint": ({"audit": str(headless(tmp_path / "h.db"))},
                                              "h.db"),
        "audit in an uncreatable directory": ({"audit": "/proc/nope/a.db"}, "/proc/nope"),
    }  # fmt: skip
    for name, (override, needle) in bad_cases.items():
        path = tmp_path / f"{name.replace(' ', '-')}.yaml"
        path.write_text(yaml.safe_dump({**good, **override}))
        checked = one_line_error(run(main, ["config", "check", str(path)]), needle)
        served = one_line_error(run(main, ["serve", "--config", str(path), "--port", "1"]), needle)
        assert checked == served, name
    ok = tmp_path / "ok.yaml"
    ok.write_text(yaml.safe_dump(good))
    assert run(main, ["config", "check", str(ok)]).exit_code == 0


def test_usage_errors_are_one_line_and_help_still_shows() -> None:
    run = CliRunner().invoke
    one_line_error(run(main, ["no-such-command"]), "no-such-command")
    bare = run(main, [])
    assert "Usage: " in bare.output and "Commands:" in bare.output and "error" not in bare.output
    assert run(main, ["--help"]).exit_code == 0


# --- help: every option explained, plain text, one name per command ------------------------------


def _commands(
    command: click.Command, path: tuple[str, ...] = ("antireplay",)
) -> list[tuple[tuple[str, ...], click.Command]]:
    found = [(path, command)]
    if isinstance(command, click.Group):
        for name, sub in command.commands.items():
            found += _commands(sub, (*path, name))
    return found


def test_every_option_of_every_command_has_help() -> None:
    missing = [
        f"{' '.join(path)} {param.opts[0]}"
        for path, command in _commands(main)
        for param in command.params
        if isinstance(param, click.Option) and not (param.help or "").strip()
    ]
    assert missing == []


def test_help_is_plain_text_without_markup() -> None:
    for path, _ in _commands(main):
        shown = CliRunner().invoke(main, [*path[1:], "--help"])
        assert shown.exit_code == 0, path
        assert "``" not in shown.output and ":func:" not in shown.output, path


def test_each_command_is_listed_once_and_its_old_name_still_runs() -> None:
    listed = CliRunner().invoke(main, ["--help"]).output
    assert "mavlink-router" in listed and "mavlink-proxy" not in listed
    old = CliRunner().invoke(main, ["mavlink-proxy", "--help"])
    assert old.exit_code == 0 and "--vehicle" in old.output


def test_mavlink_keys_add_is_idempotent(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Run twice, the file holds one line; a new passphrase replaces the endpoint's line,
    other lines stay; --signing-keys reads the result."""
    run = CliRunner().invoke
    path = tmp_path / "mavproxy" / "signing.keys"
    monkeypatch.setenv("MAV_PASSPHRASE", "first-pass")
    add = ["mavlink-keys", "add", "udpout:127.0.0.1:14550", "--file", str(path)]
    assert run(main, add).stdout == f"{path}: udpout:127.0.0.1:14550 added\n"
    again = run(main, add)
    assert again.stdout == f"{path}: udpout:127.0.0.1:14550 already has this passphrase\n"
    assert path.read_text() == "udpout:127.0.0.1:14550 first-pass\n"
    assert path.stat().st_mode & 0o777 == 0o600
    path.write_text(path.read_text() + "udpin:0.0.0.0:14551 other\n")
    monkeypatch.setenv("MAV_PASSPHRASE", "second-pass")
    assert run(main, add).stdout == f"{path}: udpout:127.0.0.1:14550 replaced\n"
    assert path.read_text() == "udpin:0.0.0.0:14551 other\nudpout:127.0.0.1:14550 second-pass\n"
    assert link_key("udpout:127.0.0.1:14550", read_signing_keys(path), None) == passphrase_key(
        "second-pass"
    )
    monkeypatch.setenv("MAV_PASSPHRASE", "two words")
    one_line_error(run(main, add), "one word")
    monkeypatch.delenv("MAV_PASSPHRASE")
    one_line_error(run(main, add), "MAV_PASSPHRASE", "not set")


def test_mavlink_sim_on_a_pty_signs_its_telemetry(tmp_path: Path) -> None:
    """The simulated vehicle on a pseudo-terminal: what the router would read from the
    printed path verifies with the key (wall-anchored, increasing timestamps)."""
    key = bytes(range(32))
    sim = SimVehicle(key, pty=True)
    try:
        assert sim.pty_path is not None and sim.where == f"{sim.pty_path},115200"
        reader = open(sim.pty_path, "rb", buffering=0)  # noqa: SIM115 - closed below
        try:
            sim.telemetry()
            sim.telemetry()
            ground = mavlink2.MAVLink(None)
            ground.signing.secret_key = key
            got: list[str] = []
            while len(got) < 4:
                got += [m.get_type() for m in ground.parse_buffer(reader.read(512)) or []]
        finally:
            reader.close()
    finally:
        sim.close()
    assert got == ["HEARTBEAT", "ATTITUDE", "HEARTBEAT", "ATTITUDE"]
    assert sim.counts == {"heartbeat": 2, "attitude": 2}
