"""``antireplay mavlink-router`` / ``mavlink-proxy``: option errors as one line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.harness import free_port, free_udp_port


@pytest.mark.parametrize(("host", "why"), [("192.0.2.1", "assign"), ("bad..host", "label")])
def test_mavlink_router_metrics_host_errors_name_the_option(
    tmp_path: Path, host: str, why: str
) -> None:
    key = tmp_path / "link.key"
    key.write_bytes(bytes(range(32)))
    args = ["mavlink-proxy", "--forward", "udp:127.0.0.1:9", "--key-file", str(key),
            "--audit", str(tmp_path / "audit.db"), "--store", "memory",
            "--listen", f"udp:127.0.0.1:{free_udp_port()}",
            "--metrics-port", str(free_port()), "--metrics-host", host]  # fmt: skip
    script = Path(sys.executable).with_name("antireplay")  # a process: metrics are global
    done = subprocess.run([script, *args], capture_output=True, text=True, timeout=60, check=False)
    assert (done.returncode, done.stdout) == (2, ""), done.stderr
    (line,) = done.stderr.splitlines()
    assert line.startswith("antireplay: error: --metrics-host " + host) and why in line, line
