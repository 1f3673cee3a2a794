"""``antireplay mavlink-pq``: the README's two-ended setup, run as written (hybrid keys)."""

from __future__ import annotations

import os
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from click.testing import CliRunner
from prometheus_client.parser import text_string_to_metric_families

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil

from antireplay.audit import verify
from antireplay.cli import main
from antireplay.mavlink.pq.wire import HANDSHAKE_SHARE, status_frame
from harness import free_port, free_udp_port, metrics_pq, until
from harness.flood import flood_until_rotated, trail_bytes
from harness.pq_radio import Plan, make_keys, run_pq
from harness.radio import SIK_BAUD, SIK_QUEUE_BYTES, Radio

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
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{free_udp_port()}", source_system=1)
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
    assert vehicle.said(f"mavlink-pq vehicle: fc udpout:127.0.0.1:{fc_port}, air udpin:")
    assert ground.said(f"mavlink-pq ground: local udpin:127.0.0.1:{local}, air udpout:")
    for end in (ground, vehicle):  # a PQ end never starts fenced, and says why
        assert end.said("; no restart fence: every session's keys are new at its handshake")


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


class Relay:
    """The air path (MAVProxy, say) on loopback: it drops everything until :attr:`opened`,
    as a MAVProxy that has not bound its port yet would, then carries datagrams both ways."""

    def __init__(self, vehicle_port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = int(self.sock.getsockname()[1])
        self.vehicle = ("127.0.0.1", vehicle_port)
        self.ground: tuple[str, int] | None = None
        self.dropped, self.opened = 0, False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, peer = self.sock.recvfrom(65536)
            except TimeoutError:
                continue
            if peer != self.vehicle:
                self.ground = peer
            if not self.opened:
                self.dropped += 1
            elif peer == self.vehicle and self.ground is not None:
                self.sock.sendto(data, self.ground)
            elif peer != self.vehicle:
                self.sock.sendto(data, self.vehicle)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self.sock.close()


def _samples(port: int) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    text = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=10).text
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def _audited(path: Path) -> list[tuple[str, str]]:
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return [(o, c) for o, c in db.execute("SELECT outcome, code FROM audit ORDER BY seq")]
    finally:
        db.close()


def test_a_lost_first_handshake_is_retried_and_each_end_reports_its_session(
    keys: Path,
) -> None:
    """The README's start order: the ground end hand-shakes before the air path carries
    anything, and no ground station sends.  The timer pokes and retries; each end logs and audits
    the session once, counts (not logs) the telemetry it had no session for, serves its
    metrics, and prints its counts at SIGTERM."""
    air, fc_port, ground_metrics, vehicle_metrics = (free_port() for _ in range(4))
    relay = Relay(air)
    ground = Process(
        [
            "mavlink-pq", "ground", "--local", f"udpin:127.0.0.1:{free_udp_port()}",
            "--air", f"udpout:127.0.0.1:{relay.port}", "--signing-key", "gcs.key.pem",
            "--vehicle-key", "vehicle.pub.pem", "--vehicle-x25519", "vehicle-x.pub.pem",
            "--audit", "ground.db", "--metrics-port", str(ground_metrics),
            "--air-bps", "10000000",  # a fast line: the retry is not held for the budget
        ],
        keys,
    )  # fmt: skip
    vehicle = Process(
        [
            "mavlink-pq", "vehicle", "--fc", f"udpin:127.0.0.1:{fc_port}",
            "--air", f"udpin:127.0.0.1:{air}", "--kem-key", "vehicle.key.pem",
            "--peer", "gcs=gcs.pub.pem", "--x25519-key", "vehicle-x.key.pem",
            "--audit", "vehicle.db", "--metrics-port", str(vehicle_metrics),
        ],
        keys,
    )  # fmt: skip
    fc = mavutil.mavlink_connection(f"udpout:127.0.0.1:{fc_port}", source_system=1)
    no_session = ("antireplay_mavlink_pq_dropped_total", (
        ("end", "vehicle"), ("reason", "NO_SESSION"), ("side", "local"),
    ))  # fmt: skip
    try:
        until("both ends running", lambda: ground.said("mavlink-pq ground") and vehicle.said(
            "mavlink-pq vehicle"))  # fmt: skip
        until("the first handshake lost", lambda: relay.dropped >= 26)  # HS1: 26 chunks

        def telemetry_dropped() -> bool:
            fc.mav.heartbeat_send(2, 3, 0, 0, 4)
            return _samples(vehicle_metrics).get(no_session, 0) >= 20

        until("telemetry without a session counted", telemetry_dropped)
        relay.opened = True
        until("the ground end's session", lambda: ground.said("session established"))
        until("the vehicle end's session", lambda: vehicle.said("session established"))
        fc.mav.heartbeat_send(2, 3, 0, 0, 4)
        ground_counts = _samples(ground_metrics)
        established = ("end", "ground"), ("event", "established")
        assert ground_counts["antireplay_mavlink_pq_sessions_total", established] == 1
        assert ground_counts["antireplay_mavlink_pq_session_up", (("end", "ground"),)] == 1
        started = ground_counts[
            "antireplay_mavlink_pq_handshakes_total", (("end", "ground"), ("outcome", "started"))
        ]
        poked = ground_counts[
            "antireplay_mavlink_pq_repairs_total", (("end", "ground"), ("what", "poke_sent"))
        ]
        assert started + poked >= 2  # it asked again by itself: a POKE or a new handshake
    finally:
        fc.close()
        ground_code, vehicle_code = ground.stop(), vehicle.stop()
        relay.close()
    assert ground_code == vehicle_code == 0
    for end in (ground, vehicle):
        assert sum("session established" in line for line in end.lines) == 1, end.lines
        assert not any("no session" in line for line in end.lines), end.lines
        assert end.said("sessions established=1"), end.lines  # the counts at SIGTERM
    assert vehicle.said("fc:NO_SESSION="), vehicle.lines  # the vehicle end's local side: the FC
    for trail in ("ground.db", "vehicle.db"):
        assert _audited(keys / trail) == [("session", "ESTABLISHED")], _audited(keys / trail)


def test_the_system_id_options_say_what_they_set() -> None:
    for end in ("ground", "vehicle"):
        result = CliRunner().invoke(main, ["mavlink-pq", end, "--help"])
        assert "system id of the PQ_CHUNK frames this end sends" in " ".join(result.output.split())


def test_commands_cross_a_lossy_slow_radio_once_each(tmp_path: Path) -> None:
    """Both ends as commands with ``--air-bps 57600``, through a real UDP radio losing
    10 % of datagrams (seeded) at 57,600 baud with a SiK-sized queue, a pymavlink ground
    station retrying as QGroundControl does and a pymavlink vehicle: the session comes up
    within 5 s, every command is executed once and acknowledged, and no retry after a lost
    ACK runs a command again (the retry is answered from what the ends hold)."""
    make_keys(tmp_path)
    plan = Plan(
        commands=8, tries=4, retry_s=1.5, session_timeout_s=30.0,
        queue_bytes=SIK_QUEUE_BYTES, keys=tmp_path, air_bps=True,
    )  # fmt: skip
    row = run_pq(0.10, SIK_BAUD, 3, plan)
    assert row.note == "" and row.session_s is not None and row.session_s < 5.0
    assert row.delivered >= 7, row  # 8 in every run so far; one may need all 4 tries
    assert row.replays == row.re_executed == row.unacked_executed == 0, row


SEGMENT, BUDGET = 65_536, 131_072  # the smallest segments; a budget of two


def test_a_vehicle_ends_trail_stays_within_its_configured_budget_under_a_refusal_flood(
    keys: Path,
) -> None:
    """``audit:`` in the end's ``--config`` reaches its trail: frames that are no chunk
    flooding the air port are refused and recorded, the trail rotates and retention keeps
    it within ``audit.max_bytes``; ``audit verify`` proves the chain from where it was cut."""
    audit, air = keys / "vehicle.db", free_udp_port()
    config = keys / "vehicle.yaml"
    config.write_text(
        f"audit: {{path: {audit}, segment_bytes: {SEGMENT}, segment_age_s: 1, "
        f"max_bytes: {BUDGET}}}\n"
        "mavlink_pq:\n  vehicle:\n"
        f"    fc: udpout:127.0.0.1:{free_udp_port()}\n    air: udpin:127.0.0.1:{air}\n"
        f"    kem_key: {keys / 'vehicle.key.pem'}\n    peers: {{gcs: {keys / 'gcs.pub.pem'}}}\n"
    )
    end = Process(["mavlink-pq", "vehicle", "--config", str(config)], keys)
    try:
        until("the vehicle end runs", lambda: end.said("mavlink-pq vehicle"))
        frames = [status_frame(1, system, 1) for system in range(2, 200)]  # no chunks
        flood_until_rotated(air, frames, audit, segments=2)
    finally:
        assert end.stop() == 0, end.lines
    assert end.said("refused") and end.said("removed by retention"), end.lines[-5:]
    assert trail_bytes(audit) <= BUDGET
    report = verify(audit)
    assert report.ok and report.first_segment > 2, report


@pytest.mark.parametrize(
    ("which", "yaml_text", "said"),
    [
        ("ground", "signing_key: gcs.key.pem\n",
         "signing_key: not a top-level key; it belongs under mavlink_pq.ground:"),
        ("vehicle", "mavlink_pq:\n  ground:\n    kem_key: k.pem\n",
         "mavlink_pq.ground.kem_key: not a key of mavlink_pq.ground:; it belongs under "
         "mavlink_pq.vehicle:"),
        ("ground", "mavlink_pq:\n  signing_key: gcs.key.pem\n",
         "mavlink_pq.signing_key: not a key of mavlink_pq:; it belongs under "
         "mavlink_pq.ground:"),
        ("vehicle", "dds:\n  psk_file: f.psk\n  peers: {gcs: gcs.pub.pem}\n",
         "dds.peers: not a key of dds:; it belongs under mavlink_pq.vehicle:"),
    ],
)  # fmt: skip
def test_a_pq_key_outside_its_block_is_refused_by_name(
    tmp_path: Path, which: str, yaml_text: str, said: str
) -> None:
    config = tmp_path / "pq.yaml"
    config.write_text(yaml_text)
    done = subprocess.run(
        [*CLI, "mavlink-pq", which, "--config", str(config), "--air", "udpin:127.0.0.1:0"],
        capture_output=True, text=True, timeout=60, check=False, cwd=tmp_path,
    )  # fmt: skip
    assert (done.returncode, done.stdout) == (2, ""), done.stderr
    (line,) = done.stderr.splitlines()
    assert line.startswith("antireplay: error: ") and said in line, line
    assert not (tmp_path / ".antireplay").exists()


def test_a_pq_end_exports_its_readiness_and_trail_as_the_gateway_does(tmp_path: Path) -> None:
    with metrics_pq(tmp_path) as port:
        text = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=10).text
    assert 'antireplay_ready{command="mavlink-pq ground"} 1.0' in text
    assert 'antireplay_audit_trail_segments{command="mavlink-pq ground"} 1.0' in text


def test_a_private_key_open_to_others_is_warned_about_by_its_flag_or_its_key(keys: Path) -> None:
    """Wiring loads the ends' keys; the CLI checks the private ones first: one warning line
    each, named by its flag or by its key in ``--config`` (a public key may be shared)."""
    for name in ("gcs.key.pem", "gcs.pub.pem", "vehicle.key.pem", "vehicle.pub.pem"):
        (keys / name).chmod(0o644)
    (keys / "audit.db").write_bytes(b"not a trail")
    (keys / "pq.yaml").write_text("mavlink_pq:\n  vehicle: {kem_key: vehicle.key.pem}\n")
    cli = [sys.executable, "-m", "antireplay", "mavlink-pq"]
    runs = {
        "--signing-key gcs.key.pem": [*cli, "ground", "--air", "udpout:127.0.0.1:9",
            "--signing-key", "gcs.key.pem", "--vehicle-key", "vehicle.pub.pem"],
        "mavlink_pq.vehicle.kem_key vehicle.key.pem": [*cli, "vehicle", "--config", "pq.yaml",
            "--fc", "udpout:127.0.0.1:9", "--air", "udpin:127.0.0.1:0",
            "--peer", "gcs=gcs.pub.pem"],
    }  # fmt: skip
    for named, args in runs.items():
        done = subprocess.run(
            [*args, "--audit", "audit.db"], capture_output=True, text=True, timeout=60,
            check=False, cwd=keys,
        )  # fmt: skip
        assert done.returncode == 2, done.stderr
        assert done.stderr.splitlines()[0] == (
            f"antireplay: warning: {named} is open to group or others (mode 0644); "
            f"keep a secret mode 0600: chmod 600 {named.split()[1]}"
        ), done.stderr
        assert "audit.db is not an antireplay audit trail" in done.stderr.splitlines()[1]


AIR_BPS = 57_600
#: What the misconfigured ground end may put on the air at once beyond its 5 % share: one
#: HS1 with its parity (29 chunks, about 7.5 KB; 7.9 KB allows for the identity's length).
#: Past it, 5 % of 57,600 baud: 288 bytes a second.
ALLOWANCE = 7_900
WINDOW_S = 12.0


def test_a_ground_end_with_the_wrong_signing_key_is_told_why_and_stays_within_its_airtime(
    keys: Path,
) -> None:
    """Finding 4: a ground end signing with a key the vehicle does not know.  The vehicle
    end answers its HS1 with a ``PQ_REFUSAL``; the ground end verifies it and logs the
    reason once, within seconds; what it puts on the air (counted at the relay between
    them) stays within 5 % of ``--air-bps`` over the run, plus the first-attempt allowance
    (on main: an HS1 every 2 s and its repairs, silent)."""
    assert (
        CliRunner()
        .invoke(main, ["keygen", "--alg", "ml-dsa-87", "--out", str(keys / "stranger")])
        .exit_code
        == 0
    )
    air = free_udp_port()
    vehicle = Process(
        [
            "mavlink-pq", "vehicle", "--fc", f"udpout:127.0.0.1:{free_udp_port()}",
            "--air", f"udpin:127.0.0.1:{air}", "--kem-key", "vehicle.key.pem",
            "--peer", "gcs=gcs.pub.pem", "--x25519-key", "vehicle-x.key.pem",
            "--audit", "vehicle.db", "--air-bps", str(AIR_BPS),
        ],
        keys,
    )  # fmt: skip
    until("the vehicle end listening", lambda: vehicle.said("mavlink-pq vehicle"))
    with Radio(("127.0.0.1", air)) as relay:
        ground = Process(
            [
                "mavlink-pq", "ground", "--local", f"udpin:127.0.0.1:{free_udp_port()}",
                "--air", f"udpout:127.0.0.1:{relay.port}", "--signing-key",
                "stranger.key.pem", "--vehicle-key", "vehicle.pub.pem",
                "--vehicle-x25519", "vehicle-x.pub.pem", "--audit", "ground.db",
                "--air-bps", str(AIR_BPS),
            ],
            keys,
        )  # fmt: skip
        refused = "vehicle refused the handshake: HS1 signature does not verify"
        try:
            until("the refusal told", lambda: ground.said(refused), timeout=10)

            def within_budget_until_the_window_ends() -> bool:
                up = relay.counts()["uplink"]
                elapsed = time.monotonic() - (up.first_at or time.monotonic())
                budget = HANDSHAKE_SHARE * AIR_BPS / 10 * elapsed + ALLOWANCE
                assert up.received_bytes <= budget, (up.received_bytes, elapsed)
                return elapsed >= WINDOW_S

            until("the measurement window", within_budget_until_the_window_ends, timeout=20)
        finally:
            ground_code, vehicle_code = ground.stop(), vehicle.stop()
        sent = relay.counts()["uplink"].received_bytes
        started = relay.counts()["uplink"].first_at or 0.0
    assert ground_code == vehicle_code == 0
    assert sum(refused in line for line in ground.lines) == 1, ground.lines
    assert "(check --signing-key here" in next(x for x in ground.lines if refused in x)
    assert ("rejected", "SIGNATURE_INVALID") in _audited(keys / "vehicle.db")
    assert sent <= HANDSHAKE_SHARE * AIR_BPS / 10 * (time.monotonic() - started) + ALLOWANCE
