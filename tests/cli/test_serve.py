"""``antireplay serve`` and ``config check``: the working directory on ``sys.path``, TLS
files, and a check that opens the store as ``serve`` would."""

from __future__ import annotations

import gc
import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest
import yaml
from click.testing import CliRunner, Result
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from antireplay.audit import AuditLog, tail
from antireplay.audit.segments import bytes_of
from antireplay.cli import main
from antireplay.cli._common import importable_cwd
from antireplay.cli.demo import JSON, command, load_operator_key, write_demo_config
from antireplay.cli.serve import settled_heap
from antireplay.rcan.auth import write_key_pair
from antireplay.state.sqlite import SqliteStore
from harness import (
    GatewayProcess,
    antireplay,
    child_pids,
    free_port,
    metric,
    one_line_error,
    post,
    serving,
    signed_by,
    until,
    wait_past_fence,
)
from harness.redis_server import RedisServer


def test_the_working_directory_goes_on_sys_path_only_for_a_module_upstream(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    for upstream in (None, "http://robot:8000/cmd", "https://robot/cmd"):
        importable_cwd(upstream)
        assert str(tmp_path) not in sys.path, upstream
    config = yaml.safe_load(write_demo_config(tmp_path).read_text())
    with socket.socket() as robot:  # config check connects to an HTTP upstream: one listens
        robot.bind(("127.0.0.1", 0))
        robot.listen()
        http = f"http://127.0.0.1:{robot.getsockname()[1]}/x"
        for upstream, added in ((http, False), ("antireplay.cli.demo:robot", True)):
            (tmp_path / "c.yaml").write_text(yaml.safe_dump({**config, "upstream": upstream}))
            result = CliRunner().invoke(main, ["config", "check", str(tmp_path / "c.yaml")])
            assert result.exit_code == 0, result.output
            assert (str(tmp_path) in sys.path) is added, upstream


def test_a_bad_tls_certificate_or_key_is_one_line_naming_both(tmp_path: Path) -> None:
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    cert.write_text("not a certificate\n")
    key.write_text("not a key\n")
    args = ["serve", "--state-dir", str(tmp_path / "state"), "--port", "0"]
    result = CliRunner().invoke(
        main, [*args, "--ssl-certfile", str(cert), "--ssl-keyfile", str(key)]
    )
    one_line_error(result, "--ssl-certfile", str(cert), "--ssl-keyfile", str(key), "PEM")


def config_check(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, text: str) -> Result:
    """``config check`` on ``text`` run from ``tmp_path`` (its relative paths, as an operator
    runs it)."""
    (tmp_path / "antireplay.yaml").write_text(text)
    monkeypatch.chdir(tmp_path)
    return CliRunner().invoke(main, ["config", "check", "antireplay.yaml"])


def test_config_check_reaches_the_redis_store(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``config check`` opens the store as ``serve`` does: an unreachable Redis fails it
    with one line naming the store, instead of passing a configuration that cannot start."""
    said = config_check(tmp_path, monkeypatch, "store: redis://127.0.0.1:1/0\naudit: audit.db\n")
    assert said.exit_code == 2, said.output
    errors = [line for line in said.stderr.splitlines() if line.strip()]
    assert len(errors) == 1 and "store redis://127.0.0.1:1/0" in errors[0], said.stderr


def test_config_check_ends_with_a_verdict_and_warns_without_keys(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, redis_url: str
) -> None:
    """A reachable store passes; the last line is the verdict, and a configuration without
    keys (a gateway that refuses everything) is warned about on stderr, still exit 0."""
    said = config_check(tmp_path, monkeypatch, f"store: {redis_url}\naudit: audit.db\n")
    assert said.exit_code == 0, said.output
    assert said.stdout.strip().splitlines()[-1] == f"ok: 0 keys, store {redis_url}, audit audit.db"
    assert "warning" in said.stderr and "no keys" in said.stderr


def test_a_state_file_whose_meta_does_not_decode_refuses_serve_and_config_check(
    tmp_path: Path,
) -> None:
    """A hand-edited meta row: ``serve`` (a real process) refuses to start with one line
    naming the file and the recovery, exit 2; ``config check`` refuses it the same way."""
    config = write_demo_config(tmp_path)
    db = tmp_path / "state.db"
    SqliteStore(db).close()
    edited = sqlite3.connect(db)
    edited.execute("UPDATE meta SET watermark = 'abc'")
    edited.commit()
    edited.close()
    one_line_error(CliRunner().invoke(main, ["config", "check", str(config)]), str(db), "mv ")
    served = subprocess.run(
        [sys.executable, "-m", "antireplay", "serve", "--config", str(config), "--port", "0"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert served.returncode == 2, served.stderr
    lines = served.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("antireplay: error: "), served.stderr
    assert str(db) in lines[0] and "mv " in lines[0]


def _restore_after_accepting(tmp_path: Path, anchor: dict[str, object] | None) -> tuple[int, str]:
    """Gateway A accepts a command, then X; the whole state directory is copied between
    the two (a VM snapshot, a backup) and restored after A stopped; gateway B, a new
    ``antireplay serve`` on the restored directory, is sent X again.  Returns B's answer
    to X and what B said on stderr."""
    state, snapshot = tmp_path / "state", tmp_path / "snapshot"
    state.mkdir()
    config = write_demo_config(state)
    if anchor is not None:
        written = yaml.safe_load(config.read_text())
        config.write_text(yaml.safe_dump({**written, "state": {"anchor": anchor}}))
    key = load_operator_key(state)
    a = GatewayProcess(config)
    a.start()
    try:
        assert post(a, command(key)).status_code == 200
        shutil.copytree(state, snapshot)  # everything in it: database, WAL, witness, audit
        x = command(key)
        assert post(a, x).status_code == 200
    finally:
        a.stop()
    shutil.rmtree(state)
    shutil.copytree(snapshot, state)
    b = GatewayProcess(config)
    b.start()
    try:
        replay = post(b, x)
        estop = post(b, command(key, type=6, safety_event="ESTOP", cmd="estop"))
        assert estop.status_code == 200, estop.text  # a fresh ESTOP passes whatever else
        losses = metric(b, "antireplay_state_data_loss_total", '{backend="sqlite"}')
    finally:
        b.stop()
    lost = [  # loss rows (the first start's "no history" row is not one)
        r for r in AuditLog(state / "audit.db").tail(50)
        if r.code == "STATE_LOST" and not str(r.warning).startswith("no history")
    ]  # fmt: skip
    assert (losses == 1) is (anchor is not None) and bool(lost) is (losses == 1)
    return replay.status_code, b.stderr_text or ""


def test_a_restored_state_directory_is_fenced_by_its_anchor(tmp_path: Path) -> None:
    """With ``state.anchor`` on another path (volume), the restored copy is behind its
    anchor: B refuses the replay (the loss fence), audits STATE_LOST and counts it."""
    (tmp_path / "other-volume").mkdir()
    anchor = str(tmp_path / "other-volume" / "state.anchor")
    status, said = _restore_after_accepting(tmp_path, {"path": anchor})
    assert status == 408, said
    assert "behind its state anchor" in said


def test_without_an_anchor_a_restored_state_directory_reopens_the_replay(
    tmp_path: Path,
) -> None:
    """The documented limitation, shown: without an anchor the restored directory agrees
    with itself and B accepts X again; the startup says so (and config check warns)."""
    status, said = _restore_after_accepting(tmp_path, None)
    assert status == 200
    assert "no state anchor" in said and "config check" in said, said
    checked = CliRunner().invoke(
        main, ["config", "check", str(tmp_path / "state" / "antireplay.yaml")]
    )
    assert checked.exit_code == 0, checked.output
    assert "no state anchor" in checked.stderr and "re-opens" in checked.stderr


def test_serve_refers_to_the_anchor_warning_that_config_check_gives_in_full(
    tmp_path: Path,
) -> None:
    """Every ``serve`` start names the missing anchor in one short line pointing at the
    full warning (``config check``, the threat model); ``config check`` keeps it whole."""
    config = write_demo_config(tmp_path)
    with serving(config) as gateway:
        pass
    warnings = [line for line in (gateway.stderr_text or "").splitlines() if "warning" in line]
    assert warnings == [
        "antireplay: warning: no state anchor: a restored snapshot can re-open replays (see "
        "`antireplay config check`, docs/threat-model.md#the-state-anchor)"
    ]
    checked = subprocess.run(
        [sys.executable, "-m", "antireplay", "config", "check", str(config)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert checked.returncode == 0, checked.stderr
    assert "replay_window_s (30 s) of a command re-opens that command's replay" in checked.stderr


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=lambda s: s.name)
def test_serve_stops_on_sigint_and_sigterm_with_a_summary_and_exit_0(
    tmp_path: Path, stop: signal.Signals
) -> None:
    """Ctrl-C and SIGTERM alike: one line saying what the gateway answered, exit 0 (not
    ``antireplay: error: aborted`` and 1, nor a silent 143)."""
    config = write_demo_config(tmp_path)
    gateway = GatewayProcess(config)
    gateway.start()
    assert gateway.proc is not None
    raw = command(load_operator_key(tmp_path))
    assert post(gateway, raw).status_code == 200
    assert post(gateway, raw).status_code == 409
    gateway.proc.send_signal(stop)
    _, err = gateway.proc.communicate(timeout=30)
    said = err.decode()
    assert gateway.proc.returncode == 0, said
    assert said.splitlines()[-1] == f"stopped by {stop.name}: served 1 accepted, 1 refused", said
    assert "aborted" not in said and "Traceback" not in said


def test_demo_stopped_by_ctrl_c_says_so_exits_0_and_leaves_no_gateway(tmp_path: Path) -> None:
    demo = subprocess.Popen(
        [sys.executable, "-m", "antireplay", "demo"], env={**os.environ, "TMPDIR": str(tmp_path)},
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:  # its gateway opened its audit trail: the demo has long had its process in hand
        until("its gateway running", lambda: list(tmp_path.glob("antireplay-demo-*/audit.db")))
        (gateway,) = child_pids(demo.pid)
        demo.send_signal(signal.SIGINT)
        _, err = demo.communicate(timeout=60)
    finally:
        demo.kill()
    assert demo.returncode == 0, err
    assert err.splitlines()[-1] == (
        "stopped by SIGINT: the demo did not finish, so it has no verdict"
    ), err
    assert "aborted" not in err and not Path(f"/proc/{gateway}").exists()


def test_config_check_names_the_anchor_and_refuses_a_bad_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An anchor passes without the no-anchor warning (one on the state's own filesystem
    is warned about); an unknown key under it, a memory store or a directory that is not
    there (a volume not mounted) fails with one line."""
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    head = "store: sqlite:state/state.db\naudit: audit.db\nstate:\n  anchor:\n    path: "
    logs = f"{head}{other}/a\n".replace("audit: audit.db", "audit: logs/audit.db")
    assert config_check(tmp_path, monkeypatch, logs).exit_code == 0
    said = config_check(tmp_path, monkeypatch, f"{head}{other}/a\n")
    assert said.exit_code == 0, said.output
    assert "no state anchor" not in said.stderr and "same filesystem" in said.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["antireplay.yaml", "other"]
    for bad, needle in (
        ("state:\n  anchor:\n    pth: a\n", "state.anchor.path"),
        ("store: memory\nstate:\n  anchor:\n    path: a\n", "only with a sqlite store"),
        ("state:\n  anchor:\n    path: /not/mounted/a\n", "an existing directory"),
        (f"{head}state/state.db\n", "the state database"),
        (f"{head}state/.state.db.witness\n", "the state witness"),
        (f"{head}audit.db\n", "the audit trail"),
        (f"{head}state/a.anchor\n", "inside the state directory"),
        (f"{head}other\n", "not a regular file"),
        (f"{head}/dev/null\n", "not on a real filesystem"),
        (f"{head}/proc/self/anchor\n", "not on a real filesystem"),
        (f"{head}other/notes.txt\n", "not a state anchor"),
        (f"{head}{other}/a\n    every_ms: 60000\n", "state.anchor.every_ms"),
    ):
        said = config_check(tmp_path, monkeypatch, bad)
        one_line_error(said, needle)
    assert (other / "notes.txt").read_text() == "keep me"
    assert not (tmp_path / "state").exists()  # config check creates nothing


def test_an_unreachable_redis_anchor_starts_unready_and_recovers(tmp_path: Path) -> None:
    """Its anchor's Redis down at start: ``config check`` fails with one line, but
    ``serve`` starts (a fresh ESTOP must still reach the robot), unready (/readyz 503
    naming the anchor), refusing other commands until the anchor answers; it is unready
    again while the anchor goes down while running."""
    (tmp_path / "redis").mkdir()
    server = RedisServer(tmp_path / "redis", persistent=True)
    server.start()
    server.kill()
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    written = yaml.safe_load(config.read_text())
    config.write_text(yaml.safe_dump({**written, "state": {"anchor": {"redis": server.url}}}))
    one_line_error(CliRunner().invoke(main, ["config", "check", str(config)]), "state anchor")
    key = load_operator_key(state)
    gateway = GatewayProcess(config)
    gateway.start()
    try:
        ready = httpx.get(f"{gateway.url}/readyz", timeout=5)
        assert ready.status_code == 503 and "state anchor" in ready.text, ready.text
        assert post(gateway, command(key)).status_code == 503
        estop = post(gateway, command(key, type=6, safety_event="ESTOP", cmd="estop"))
        assert estop.status_code == 200, estop.text
        server.start()
        wait_past_fence(gateway.url)  # verified now: a state with no history fences from here
        assert httpx.get(f"{gateway.url}/readyz", timeout=5).status_code == 200
        assert post(gateway, command(key)).status_code == 200
        server.kill()
        ready = httpx.get(f"{gateway.url}/readyz", timeout=5)
        assert ready.status_code == 503 and "state anchor" in ready.text, ready.text
    finally:
        gateway.stop()
        server.stop()


def test_two_gateways_on_one_anchor_file_the_second_refuses_to_start(tmp_path: Path) -> None:
    """B (its own state directory) given A's ``state.anchor.path`` refuses to start with
    one line naming the file, its owner and the recovery, instead of adopting A's
    deployment; a restore of A's directory is then still caught by A's anchor."""
    (tmp_path / "other").mkdir()
    shared = {"path": str(tmp_path / "other" / "shared.anchor")}
    configs = []
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        config = write_demo_config(tmp_path / name)
        written = yaml.safe_load(config.read_text())
        config.write_text(yaml.safe_dump({**written, "state": {"anchor": shared}}))
        configs.append(config)
    key = load_operator_key(tmp_path / "a")
    a = GatewayProcess(configs[0])
    a.start()
    try:
        assert post(a, command(key)).status_code == 200
        shutil.copytree(tmp_path / "a", tmp_path / "snapshot")
        x = command(key)
        assert post(a, x).status_code == 200
        with pytest.raises(RuntimeError) as refused:
            GatewayProcess(configs[1]).start()
    finally:
        a.stop()
    said = [line for line in str(refused.value).splitlines() if "error" in line]
    assert len(said) == 1 and shared["path"] in said[0] and "own state.anchor.path" in said[0]
    shutil.rmtree(tmp_path / "a")
    shutil.copytree(tmp_path / "snapshot", tmp_path / "a")
    with serving(configs[0]) as restored:
        assert post(restored, x).status_code == 408
        assert metric(restored, "antireplay_state_data_loss_total", '{backend="sqlite"}') == 1


def test_gateways_on_other_hostnames_share_one_redis_anchor(tmp_path: Path, redis_url: str) -> None:
    """Two gateways on one state directory, on two hostnames (UTS namespaces), one Redis
    anchor: neither start counts a loss, and after a restore of the directory the
    first host's gateway refuses X, which the second accepted."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    written = yaml.safe_load(config.read_text())
    config.write_text(yaml.safe_dump({**written, "state": {"anchor": {"redis": redis_url}}}))
    key = load_operator_key(state)

    def on(host: str) -> GatewayProcess:
        prefix = ("unshare", "-u", "sh", "-c", f'hostname {host} && exec "$@"', "sh")
        return GatewayProcess(config, prefix=prefix)

    a, b = on("host-a"), on("host-b")
    a.start()
    try:
        assert post(a, command(key)).status_code == 200
        b.start()
        assert metric(b, "antireplay_state_data_loss_total", '{backend="sqlite"}') == 0
        shutil.copytree(state, tmp_path / "snapshot")
        x = command(key)
        assert post(b, x).status_code == 200
    finally:
        a.stop()
        b.stop()
    shutil.rmtree(state)
    shutil.copytree(tmp_path / "snapshot", state)
    a = on("host-a")
    a.start()
    try:
        assert post(a, x).status_code == 408
        assert metric(a, "antireplay_state_data_loss_total", '{backend="sqlite"}') == 1
    finally:
        a.stop()


def test_a_lazy_anchors_restart_fence_is_said_like_any_fence(tmp_path: Path) -> None:
    """A restart inside a lazy anchor's lease refuses commands stamped before the lease's
    end: it says so (log line, data-loss metric, STATE_LOST audit row naming the lease),
    and a fresh ESTOP still passes."""
    (tmp_path / "other").mkdir()
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    written = yaml.safe_load(config.read_text())
    lazy = {"path": str(tmp_path / "other" / "a.anchor"), "every_ms": 10_000}
    config.write_text(yaml.safe_dump({**written, "state": {"anchor": lazy}}))
    key = load_operator_key(state)
    with serving(config) as first:
        assert post(first, command(key)).status_code == 200
    second = GatewayProcess(config)
    second.start(past_fence=False)  # the lease's fence is what this test is about
    try:
        assert post(second, command(key)).status_code == 408
        estop = post(second, command(key, type=6, safety_event="ESTOP", cmd="estop"))
        assert estop.status_code == 200, estop.text
        assert metric(second, "antireplay_state_data_loss_total", '{backend="sqlite"}') == 1
    finally:
        second.stop()
    assert "lazy state anchor's lease" in (second.stderr_text or "")
    rows = [r for r in AuditLog(state / "audit.db").tail(50) if r.code == "STATE_LOST"]
    new, lease = sorted(rows, key=lambda r: r.seq)  # the first start's, then the lease's
    assert str(new.warning).startswith("no history") and "lease" in str(lease.warning)


def _race(urls: list[str], raw: bytes, connections: int) -> list[int]:
    """``connections`` clients, each on its own connection to one of ``urls`` (in turn),
    POST ``raw`` at once; their statuses."""
    clients = [httpx.Client(base_url=urls[i % len(urls)], timeout=30) for i in range(connections)]
    for client in clients:  # connected before the race
        client.get("/healthz").raise_for_status()
    gate = threading.Barrier(connections)

    def send(client: httpx.Client) -> int:
        gate.wait()
        return post(client, raw).status_code

    try:
        with ThreadPoolExecutor(connections) as pool:
            return list(pool.map(send, clients))
    finally:
        for client in clients:
            client.close()


def _audit_intact(state: Path) -> str:
    verified = CliRunner().invoke(main, ["audit", "verify", str(state / "audit.db")])
    assert verified.exit_code == 0, verified.output
    return verified.output


def test_two_gateway_processes_on_one_state_accept_a_message_once_and_keep_one_chain(
    tmp_path: Path,
) -> None:
    """Two ``antireplay serve`` processes on one SQLite state and one audit trail, sent
    the same messages at once over 24 connections split between them: each message is
    accepted exactly once, every answer audited, and the trail is one intact chain."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    key = load_operator_key(state)
    a, b = GatewayProcess(config), GatewayProcess(config)
    a.start()
    b.start()
    try:
        messages = [command(key) for _ in range(8)]
        for raw in messages:
            statuses = _race([a.url, b.url], raw, 24)
            assert sorted(statuses) == [200] + [409] * 23, statuses
    finally:
        a.stop()
        b.stop()
    _audit_intact(state)
    rows = AuditLog(state / "audit.db").tail(500)
    assert sum(r.outcome == "accepted" for r in rows) == len(messages)


def _workers_of(pid: int) -> list[int]:
    """The gateway worker processes uvicorn's supervisor ``pid`` spawned."""
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            ppid = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmdline = (proc / "cmdline").read_bytes()
        except (FileNotFoundError, ProcessLookupError, IndexError):
            continue
        if ppid == pid and b"spawn_main" in cmdline:
            found.append(int(proc.name))
    return found


def test_serve_workers_runs_n_processes_that_accept_a_message_once(tmp_path: Path) -> None:
    """``serve --workers 2``: two worker processes on the one socket; racing copies of a
    message over many connections get exactly one 200; the trail verifies."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    key = load_operator_key(state)
    port = free_port()
    args = [sys.executable, "-m", "antireplay", "serve", "--config", str(config)]
    proc = subprocess.Popen(
        [*args, "--port", str(port), "--workers", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    try:
        until("serving", lambda: len(_workers_of(proc.pid)) == 2 and _healthy(url), 60)
        wait_past_fence(url)  # a new state: its first start's fence (its own test above)
        for _ in range(4):
            statuses = _race([url], command(key), 32)
            assert sorted(statuses) == [200] + [409] * 31, statuses
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err.decode()
    assert b"2 worker processes (metrics per process)" in out
    _audit_intact(state)


def _healthy(url: str) -> bool:
    try:
        return httpx.get(url + "/healthz", timeout=1).status_code == 200
    except httpx.HTTPError:
        return False


def test_serve_workers_refuses_the_memory_store(tmp_path: Path) -> None:
    """One process's memory is not shared: --workers 2 on a memory store is one line."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    written = yaml.safe_load(config.read_text())
    config.write_text(yaml.safe_dump({**written, "store": "memory"}))
    result = CliRunner().invoke(main, ["serve", "--config", str(config), "--workers", "2"])
    assert result.exit_code == 2
    one_line_error(result, "store", "memory", "--workers")


def test_serve_workers_rotate_and_retain_one_trail_within_its_budget(tmp_path: Path) -> None:
    """``serve --workers 2`` on one trail with a small audit budget: neither worker's open
    trail stops the other's rotation, so the trail stays within ``max_bytes`` plus one
    segment while both serve, and what retention kept verifies, each accepted row once."""
    state = tmp_path / "state"
    state.mkdir()
    budget = {"segment_bytes": 65_536, "max_bytes": 262_144}
    config = write_demo_config(state, audit={"path": str(state / "audit.db"), **budget})
    key = load_operator_key(state)
    port = free_port()
    args = [sys.executable, "-m", "antireplay", "serve", "--config", str(config)]
    proc = subprocess.Popen(
        [*args, "--port", str(port), "--workers", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    try:
        until("serving", lambda: len(_workers_of(proc.pid)) == 2 and _healthy(url), 60)
        wait_past_fence(url)  # a new state: its first start's fence (its own test above)

        def send(n: int) -> list[int]:
            with httpx.Client(base_url=url, timeout=30) as client:
                return [post(client, command(key)).status_code for _ in range(n)]

        with ThreadPoolExecutor(8) as pool:  # 8 connections, spread over the workers
            answers = [code for codes in pool.map(send, [250] * 8) for code in codes]
        assert answers == [200] * 2000
        scraped = httpx.get(url + "/metrics", timeout=10).text
        assert "antireplay_audit_rotations_postponed_total " in scraped  # counted, per process
        trail = [state / "audit.db", *state.glob("audit.db.[0-9]*")]
        on_disk = sum(bytes_of(file) for file in trail)
        assert on_disk <= budget["max_bytes"] + budget["segment_bytes"], on_disk
    finally:
        proc.terminate()
        err = proc.communicate(timeout=60)[1]
    assert proc.returncode == 0, err.decode()
    assert "segments 1–" in _audit_intact(state)  # rotated, and the oldest removed
    accepted = [r.msg_id for r in tail(state / "audit.db", 100_000) if r.outcome == "accepted"]
    assert len(accepted) == len(set(accepted)) > 100  # the rows retention kept, once each


def test_what_startup_built_is_frozen_out_of_the_collectors_sight() -> None:
    """``serve`` calls it before serving: a full collection under a flood then scans only
    what requests left (an ESTOP waited out a 30 ms pause scanning every module)."""
    gc.unfreeze()
    try:
        settled_heap()
        assert gc.get_freeze_count() > 10_000
    finally:
        gc.unfreeze()


def test_config_check_validates_every_section(tmp_path: Path) -> None:
    """``config check`` loads what the router, the PQ ends and the DDS commands would load
    from their sections (key files, allow-lists, PEM keys), and names the first that
    fails; ``serve``'s own checks run as before."""
    run = CliRunner().invoke
    config = write_demo_config(tmp_path)
    key = tmp_path / "link.key"
    key.write_bytes(bytes(range(32)))
    base = yaml.safe_load(config.read_text())
    router = {"vehicle": ["udpin:127.0.0.1:14555"], "ground": ["udpin:127.0.0.1:14550"],
              "key_file": str(key), "store": "memory"}  # fmt: skip
    config.write_text(yaml.safe_dump({**base, "mavlink": router}))
    done = run(main, ["config", "check", str(config)])
    assert done.exit_code == 0 and "ok: mavlink: 2 endpoints, store memory" in done.output
    alone = tmp_path / "router.yaml"  # a router's file: no gateway keys to warn about
    alone.write_text(yaml.safe_dump({"mavlink": router, "audit": str(tmp_path / "r.db")}))
    done = run(main, ["config", "check", str(alone)])
    assert done.exit_code == 0 and "no keys" not in done.stderr, done.stderr
    for wrong, named in (
        ({"mavlink": {**router, "key_file": str(tmp_path / "gone.key")}}, "mavlink.key_file"),
        ({"mavlink": {**router, "allow_unsigned": ["NOPE"]}}, "mavlink.allow_unsigned"),
        ({"mavlink_pq": {"vehicle": {"kem_key": str(key), "peers": {"g": "x"}}}},
         "mavlink_pq.vehicle.kem_key"),
        ({"dds": {"psk_file": str(tmp_path / "gone.psk")}}, "dds.psk_file"),
    ):  # fmt: skip
        config.write_text(yaml.safe_dump({**base, **wrong}))
        one_line_error(run(main, ["config", "check", str(config)]), named)


def test_a_wiped_state_directory_fences_its_start_and_says_so(tmp_path: Path) -> None:
    """X accepted on SQLite; the state directory wiped (database, WAL, witness, audit trail:
    a redeploy, or an attacker with the disk); the gateway starts on a state with no
    history, and X replayed within its window is refused by the restart fence, as a
    memory store's start would refuse it.  The start line, readiness, the metric and an
    audit row say "no history"."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    key = load_operator_key(state)
    with serving(config) as first:  # waits out its own first start's fence
        x = command(key)
        assert post(first, x).status_code == 200
    kept = {config.name, "operator.key.pem", "operator.pub.pem"}
    for leftover in state.iterdir():
        if leftover.name not in kept:
            shutil.rmtree(leftover) if leftover.is_dir() else leftover.unlink()
    port = free_port()
    args = [sys.executable, "-m", "antireplay", "serve", "--config", str(config)]
    proc = subprocess.Popen(
        [*args, "--host", "127.0.0.1", "--port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10) as client:
            until("the gateway to answer", lambda: _answers(client))
            replayed = post(client, x)
            body = replayed.json()
            assert (replayed.status_code, body.get("code"), body.get("detail")) == (
                408, "MESSAGE_STALE", "restart_fence",
            ), replayed.text  # fmt: skip
            ready = client.get("/readyz")
            assert ready.status_code == 503 and "fenced until" in ready.json()["reason"]
            assert "no history" in ready.json()["reason"]
            assert metric(client, "antireplay_state_no_history_total", '{backend="sqlite"}') == 1
            assert metric(client, "antireplay_state_data_loss_total", '{backend="sqlite"}') == 0
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=30)
    said = out.splitlines()
    assert said[0].startswith("listening on") and said[1].startswith("fenced until"), said
    assert "no history" in said[1]
    rows = [r for r in AuditLog(state / "audit.db").tail(50) if r.code == "STATE_LOST"]
    assert len(rows) == 1 and str(rows[0].warning).startswith("no history"), rows


def _answers(client: httpx.Client) -> bool:
    try:
        return client.get("/healthz").status_code == 200
    except httpx.HTTPError:
        return False


def test_serve_workers_each_reload_keys_and_apply_a_revocation(tmp_path: Path) -> None:
    """``serve --workers 2`` and ``antireplay keys reload``: each worker re-reads the file (a
    ``KEYS_RELOADED`` row each) and takes the rotated key; ``keys revoke`` then refuses it on
    every connection, whichever worker answers."""
    state = tmp_path / "state"
    state.mkdir()
    config = write_demo_config(state)
    new = Ed25519PrivateKey.generate()
    write_key_pair(new, state / "next.key.pem", state / "next.pub.pem")
    written = yaml.safe_load(config.read_text())
    rotated = {**written["keys"][0], "kid": "next", "public_keys": [str(state / "next.pub.pem")]}
    port = free_port()
    args = [sys.executable, "-m", "antireplay", "serve", "--config", str(config)]
    proc = subprocess.Popen(
        [*args, "--port", str(port), "--workers", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    url = f"http://127.0.0.1:{port}"

    def codes() -> set[str | None]:  # fresh commands, each on a connection of its own
        replies = [httpx.post(f"{url}/v1/messages", content=signed_by(new, "next"),
                              headers=JSON, timeout=10) for _ in range(8)]  # fmt: skip
        return {None if r.status_code == 200 else r.json()["code"] for r in replies}

    try:
        until("serving", lambda: len(_workers_of(proc.pid)) == 2 and _healthy(url), 60)
        wait_past_fence(url)
        config.write_text(yaml.safe_dump({**written, "keys": [*written["keys"], rotated]}))
        asked = antireplay("keys", "reload", "--config", str(config), cwd=tmp_path)
        assert asked.returncode == 0, asked.stderr

        def reloaded() -> bool:
            rows = AuditLog(state / "audit.db").tail(50)
            return sum(r.code == "KEYS_RELOADED" for r in rows) == 2

        until("both workers to reload", reloaded)
        assert codes() == {None}
        revoked = antireplay("keys", "revoke", "next", "--config", str(config), cwd=tmp_path)
        assert revoked.returncode == 0, revoked.stderr
        until("the revocation", lambda: codes() == {"KEY_REVOKED"}, 10)
    finally:
        proc.terminate()
        proc.communicate(timeout=60)
    assert proc.returncode == 0


def _sighup_blocked(pid: int) -> bool:
    """Whether ``pid``'s main thread blocks SIGHUP (``SigBlk`` in ``/proc``: bit 0)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigBlk:"):
            return bool(int(line.split()[1], 16) & 1)
    return False


def test_a_sighup_during_start_up_never_kills_serve_and_reloads(tmp_path: Path) -> None:
    """SIGHUP as soon as the command runs (before the reload handler exists): blocked and
    pending until the handler is in place, then one reload; the gateway serves."""
    config = write_demo_config(tmp_path)
    port = free_port()
    err = (tmp_path / "serve.err").open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "antireplay", "serve", "--config", str(config),
         "--host", "127.0.0.1", "--port", str(port)],
        stdout=subprocess.DEVNULL, stderr=err,
    )  # fmt: skip
    try:
        until("serve to block SIGHUP", lambda: proc.poll() is not None or _sighup_blocked(proc.pid))
        proc.send_signal(signal.SIGHUP)
        text = (tmp_path / "serve.err").read_text
        until("the reload", lambda: proc.poll() is not None or "keys reloaded" in text(), 30)
        assert proc.poll() is None, text()
        assert httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=10).status_code == 200
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        err.close()
