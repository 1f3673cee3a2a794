"""``antireplay mavlink-router`` / ``mavlink-proxy``: option errors as one line; exit counts."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from click.testing import CliRunner

from antireplay.audit import AuditLog
from antireplay.cli import main
from antireplay.config import AuditConfig
from tests.harness import free_port, free_udp_port, until


@pytest.mark.parametrize(("host", "why"), [("192.0.2.1", "assign"), ("bad..host", "label")])
def test_mavlink_router_metrics_host_errors_name_the_option(
    tmp_path: Path, host: str, why: str
) -> None:
    key = tmp_path / "link.key"
    key.write_bytes(bytes(range(32)))
    key.chmod(0o600)  # a secret (a wider one is warned about)
    args = ["mavlink-proxy", "--forward", "udp:127.0.0.1:9", "--key-file", str(key),
            "--audit", str(tmp_path / "audit.db"), "--store", "memory",
            "--listen", f"udp:127.0.0.1:{free_udp_port()}",
            "--metrics-port", str(free_port()), "--metrics-host", host]  # fmt: skip
    script = Path(sys.executable).with_name("antireplay")  # a process: metrics are global
    done = subprocess.run([script, *args], capture_output=True, text=True, timeout=60, check=False)
    assert (done.returncode, done.stdout) == (2, ""), done.stderr
    (line,) = done.stderr.splitlines()
    assert line.startswith("antireplay: error: --metrics-host " + host) and why in line, line


def test_mavlink_router_opens_its_trail_rotated_and_retained(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The router's trail has the ``audit:`` defaults' segments and budget, and a spill."""
    opened: list[AuditLog] = []

    def build(_endpoints: object, _store: object, audit: AuditLog, _options: object) -> None:
        opened.append(audit)
        raise ValueError("stop here")

    monkeypatch.setattr("antireplay.wiring.build_mavlink_router", build)
    key = tmp_path / "link.key"
    key.write_bytes(bytes(range(32)))
    trail = tmp_path / "audit.db"
    args = ["mavlink-router", "--forward", "udp:127.0.0.1:9", "--key-file", str(key),
            "--audit", str(trail), "--store", "memory",
            "--listen", f"udp:127.0.0.1:{free_udp_port()}"]  # fmt: skip
    done = CliRunner().invoke(main, args)
    assert done.exit_code == 2 and "stop here" in done.output, done.output
    (audit,) = opened
    audit.close()
    defaults = AuditConfig(path=str(trail))
    assert (audit.retention.segment_bytes, audit.retention.max_bytes) == (
        defaults.segment_bytes, defaults.max_bytes,
    )  # fmt: skip
    assert trail.with_name("audit.db.spill").exists()


def test_the_routers_exit_counts_say_what_no_peer_means(tmp_path: Path) -> None:
    """The simulated vehicle's telemetry, accepted with no ground station authenticated yet,
    is counted ``NO_PEER``; stopped, the router says what that means beside the count."""
    vehicle, metrics = free_udp_port(), free_port()
    env = {**os.environ, "MAV_PASSPHRASE": "correct-horse-battery-staple"}
    cli = [sys.executable, "-m", "antireplay"]
    router = subprocess.Popen(
        [*cli, "mavlink-router", "--vehicle", f"udpin:127.0.0.1:{vehicle}",
         "--ground", f"udpin:127.0.0.1:{free_udp_port()}", "--passphrase-env", "MAV_PASSPHRASE",
         "--store", f"sqlite:{tmp_path / 'state.db'}", "--audit", str(tmp_path / "audit.db"),
         "--metrics-port", str(metrics)],  # a new store: no start fence (memory's refuses 60 s)
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    sim = subprocess.Popen(
        [*cli, "mavlink-sim", "--udp", f"127.0.0.1:{vehicle}", "--passphrase-env",
         "MAV_PASSPHRASE"],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip

    def no_peer() -> bool:
        try:
            text = httpx.get(f"http://127.0.0.1:{metrics}/metrics", timeout=5).text
        except httpx.HTTPError:
            return False
        return 'code="NO_PEER"' in text

    try:
        until("telemetry dropped as NO_PEER", no_peer)
    finally:
        sim.terminate()
        sim.wait(timeout=30)
        router.send_signal(signal.SIGTERM)
        _, err = router.communicate(timeout=30)
    assert router.returncode == 0, err
    summary = err.splitlines()[-1]
    assert summary.startswith("forwarded "), err
    assert (
        ":NO_PEER " in summary
        and (
            " (accepted, but no other link had a receiver yet: telemetry before a ground station "
            "authenticated)"
        )
        in summary
    ), summary
