"""``antireplay mavlink-pq``: the README's two-ended setup, run as written (hybrid keys)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil

from antireplay.cli import main
from tests.harness import free_port, until

CLI = [sys.executable, "-m", "antireplay"]


class Process:
    """A command whose stderr lines are kept as they come."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        self.lines: list[str] = []
        self.proc = subprocess.Popen(
            [*CLI, *args], cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        self._reader = threading.Thread(target=self._read)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.append(line)

    def said(self, text: str) -> bool:
        return any(text in line for line in list(self.lines))

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        code = self.proc.wait(timeout=30)
        self._reader.join()
        return code


@pytest.fixture
def keys(tmp_path: Path) -> Path:
    runner = CliRunner()
    for alg, out in (("ml-dsa-87", "gcs"), ("ml-kem-1024", "vehicle"), ("x25519", "vehicle-x")):
        result = runner.invoke(main, ["keygen", "--alg", alg, "--out", str(tmp_path / out)])
        assert result.exit_code == 0, result.output
    return tmp_path


@pytest.fixture
def fc() -> Iterator[Any]:
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{free_port()}", source_system=1)
    try:
        yield conn
    finally:
        conn.close()


def test_ground_and_vehicle_ends_carry_arm(keys: Path, fc: Any) -> None:
    air, local = free_port(), free_port()
    fc_port = fc.port.getsockname()[1]
    vehicle = Process(
        [
            "mavlink-pq", "vehicle", "--fc", f"udpout:127.0.0.1:{fc_port}",
            "--air", f"udpin:127.0.0.1:{air}", "--kem-key", "vehicle.key.pem",
            "--peer", "gcs=gcs.pub.pem", "--x25519-key", "vehicle-x.key.pem",
        ],
        keys,
    )  # fmt: skip
    until("the vehicle end listening", lambda: vehicle.said("mavlink-pq vehicle"))
    ground = Process(
        [
            "mavlink-pq", "ground", "--local", f"udpin:127.0.0.1:{local}",
            "--air", f"udpout:127.0.0.1:{air}", "--signing-key", "gcs.key.pem",
            "--vehicle-key", "vehicle.pub.pem", "--vehicle-x25519", "vehicle-x.pub.pem",
        ],
        keys,
    )  # fmt: skip
    until("the ground end listening", lambda: ground.said("mavlink-pq ground"))
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{local}", source_system=255)
    try:
        gcs.mav.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)  # queued until the session
        until(
            "ARM at the flight controller",
            lambda: fc.recv_match(type="COMMAND_LONG", blocking=False) is not None,
        )
    finally:
        gcs.close()
        assert ground.stop() == 0 and vehicle.stop() == 0
    assert vehicle.said("forwarded air=2;"), vehicle.lines  # HS1 and the ARM


def test_bad_options_are_one_line_errors(keys: Path) -> None:
    runner = CliRunner()
    # a PKCS #8 key of an algorithm cryptography does not know (OID 1.2.3.4)
    (keys / "odd.key.pem").write_text(
        "-----BEGIN PRIVATE KEY-----\nMBACAQAwBQYDKgMEBAQEAgAA\n-----END PRIVATE KEY-----\n"
    )
    base = ["mavlink-pq", "vehicle", "--fc", "udpout:127.0.0.1:9", "--air", "udpin:127.0.0.1:0"]
    for extra, expected in (
        (["--kem-key", str(keys / "vehicle.key.pem"), "--peer", "gcs"], "expected NAME=PEM"),
        (["--kem-key", str(keys / "gcs.key.pem"), "--peer", "g=x"], "not a MLKEM1024PrivateKey"),
        (
            ["--kem-key", str(keys / "vehicle.key.pem"), "--peer", "g=nope.pem"],
            "not a PEM public key",
        ),
        (["--kem-key", str(keys / "odd.key.pem"), "--peer", "g=x"], "Unknown key type"),
    ):
        result = runner.invoke(main, [*base, *extra])
        assert result.exit_code == 2, result.output
        assert expected in result.output
