"""``antireplay mavlink-router`` / ``mavlink-proxy``: option errors as one line; exit counts."""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from click.testing import CliRunner

from antireplay.audit import AuditLog, verify
from antireplay.cli import main
from antireplay.config import AuditConfig
from harness import free_port, free_udp_port, metrics_router, until
from harness.flood import flood_until_rotated, trail_bytes
from harness.mavlink_frames import unsigned_heartbeat
from harness.mavlink_router import (
    drained,
    frames_from,
    host_address,
    router_process,
    station,
    udp_socket,
)
from harness.stores import aged_state


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
    """The router's trail has the ``audit:`` defaults' segments and budget, and a spill;
    a router that cannot be built leaves its trail closed."""
    opened: list[AuditLog] = []

    def build(_endpoints: object, _store: object, audit: AuditLog, *_: object) -> None:
        opened.append(audit)
        raise ValueError("stop here")

    monkeypatch.setattr("antireplay.wiring.mavlink.build_mavlink_router", build)
    key = tmp_path / "link.key"
    key.write_bytes(bytes(range(32)))
    trail = tmp_path / "audit.db"
    args = ["mavlink-router", "--forward", "udp:127.0.0.1:9", "--key-file", str(key),
            "--audit", str(trail), "--store", "memory",
            "--listen", f"udp:127.0.0.1:{free_udp_port()}"]  # fmt: skip
    done = CliRunner().invoke(main, args)
    assert done.exit_code == 2 and "stop here" in done.output, done.output
    (audit,) = opened  # closed again by the wiring when the router could not be built
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
         "--store", f"sqlite:{aged_state(tmp_path / 'state.db')}",
         "--audit", str(tmp_path / "audit.db"),
         "--metrics-port", str(metrics)],  # a state with history: no first start's fence
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


SEGMENT, BUDGET = 65_536, 131_072  # the smallest segments; a budget of two


def test_the_routers_trail_stays_within_its_configured_budget_under_a_refusal_flood(
    tmp_path: Path,
) -> None:
    """``audit:`` in the router's ``--config`` reaches its trail: unsigned frames flooding a
    ground link are refused and recorded, the trail rotates and retention keeps it within
    ``audit.max_bytes``; ``audit verify`` proves the chain from where retention cut it."""
    key, audit, ground = tmp_path / "link.key", tmp_path / "router.db", free_udp_port()
    key.write_bytes(bytes(range(32)))
    key.chmod(0o600)  # a secret (a wider one is warned about)
    config = tmp_path / "router.yaml"
    config.write_text(
        f"audit: {{path: {audit}, segment_bytes: {SEGMENT}, segment_age_s: 1, "
        f"max_bytes: {BUDGET}}}\n"
        f"mavlink:\n  ground: ['udpin:127.0.0.1:{ground}']\n"
        f"  vehicle: ['udpout:127.0.0.1:{free_udp_port()}']\n"
        f"  key_file: {key}\n  store: memory\n"
    )
    args = [sys.executable, "-m", "antireplay", "mavlink-router", "--config", str(config)]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and "mavlink-router" in proc.stdout.readline()
        frames = [unsigned_heartbeat(system) for system in range(2, 200)]
        flood_until_rotated(ground, frames, audit, segments=2)
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "SIGNATURE_REQUIRED" in err and "removed by retention" in err
    assert trail_bytes(audit) <= BUDGET
    report = verify(audit)
    assert report.ok and report.first_segment > 2, report


@pytest.mark.parametrize(
    ("yaml_text", "said"),
    [
        ("signing_key: op.pem\n",
         "signing_key: not a top-level key; it belongs under mavlink_pq.ground:"),
        ("key_file: link.key\n", "key_file: not a top-level key; it belongs under mavlink:"),
        ("dds:\n  psk_file: fleet.psk\n  system_id: 1\n",
         "dds.system_id: not a key of dds:; it belongs under mavlink: or mavlink_pq.ground: "
         "or mavlink_pq.vehicle:"),
        ("mavlink:\n  replay_window_s: 30\n",
         "mavlink.replay_window_s: not a key of mavlink:; it belongs under security:"),
        ("mavlink:\n  store: memroy\n", "mavlink.store='memroy'"),
    ],
)  # fmt: skip
def test_a_mavlink_key_outside_its_block_is_refused_by_name(
    tmp_path: Path, yaml_text: str, said: str
) -> None:
    """A key where it does not belong (or a value it cannot take) stops the router before
    it opens anything: one line naming the key and where it belongs, status 2."""
    config = tmp_path / "router.yaml"
    config.write_text(yaml_text)
    args = [sys.executable, "-m", "antireplay", "mavlink-router", "--config", str(config),
            "--forward", "udp:127.0.0.1:9"]  # fmt: skip
    done = subprocess.run(
        args, capture_output=True, text=True, timeout=60, check=False, cwd=tmp_path
    )
    assert (done.returncode, done.stdout) == (2, ""), done.stderr
    (line,) = done.stderr.splitlines()
    assert line.startswith("antireplay: error: ") and said in line, line
    assert not (tmp_path / ".antireplay").exists()


def test_flags_override_the_config_file(tmp_path: Path) -> None:
    """``--store`` over ``mavlink.store``: the flag's value is held to the key's rules and
    named by its flag when it breaks them."""
    config = tmp_path / "router.yaml"
    config.write_text("mavlink:\n  store: memory\n  vehicle: ['udpout:127.0.0.1:9']\n")
    args = ["mavlink-router", "--config", str(config), "--store", "bogus:x"]
    done = CliRunner().invoke(main, args)
    assert done.exit_code == 2
    assert done.output.startswith("antireplay: error: --store: invalid config mavlink.store")


def test_the_router_exports_its_readiness_and_trail_as_the_gateway_does(tmp_path: Path) -> None:
    with metrics_router(tmp_path) as port:
        text = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=10).text
    assert 'antireplay_ready{command="mavlink-router"} 1.0' in text
    assert 'antireplay_audit_trail_segments{command="mavlink-router"} 1.0' in text
    assert 'antireplay_audit_disk_pressure{command="mavlink-router"} 0.0' in text


@pytest.mark.parametrize("given", ["flag", "config"])
def test_a_link_key_open_to_others_is_warned_about_by_its_flag_or_its_key(
    tmp_path: Path, given: str
) -> None:
    """The router reads its key files through wiring; the CLI checks them first: a key file
    group or others may read gets one warning line naming the flag, or the key of the file
    that named it (here the run then stops at a trail that is not one)."""
    key, keys = tmp_path / "link.key", tmp_path / "signing.keys"
    key.write_bytes(bytes(range(32)))
    keys.write_text("udpin:127.0.0.1:9 passphrase\n")
    key.chmod(0o644)
    keys.chmod(0o640)
    (tmp_path / "audit.db").write_bytes(b"not a trail")
    args = ["--forward", "udp:127.0.0.1:9", "--audit", "audit.db"]
    if given == "flag":
        args += ["--key-file", "link.key", "--signing-keys", "signing.keys"]
        named = ("--key-file", "--signing-keys")
    else:
        (tmp_path / "router.yaml").write_text(
            "mavlink: {key_file: link.key, signing_keys: signing.keys}\n"
        )
        args += ["--config", "router.yaml"]
        named = ("mavlink.key_file", "mavlink.signing_keys")
    done = subprocess.run(
        [sys.executable, "-m", "antireplay", "mavlink-router", *args],
        capture_output=True, text=True, timeout=60, check=False, cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    warned, failed = done.stderr.splitlines()[:2], done.stderr.splitlines()[2]
    assert warned == [
        f"antireplay: warning: {named[0]} link.key is open to group or others (mode 0644); "
        "keep a secret mode 0600: chmod 600 link.key",
        f"antireplay: warning: {named[1]} signing.keys is open to group or others (mode 0640); "
        "keep a secret mode 0600: chmod 600 signing.keys",
    ], done.stderr
    assert failed.startswith("antireplay: error: audit.db is not an antireplay audit trail")


# --- issue 35: authority stays local, spikes bounded in time, fences explained ---------------


def router_args(tmp_path: Path, *extra: str, store: str | None = None) -> list[str]:
    """A router's flags: a state with history (no first start's fence) unless ``store``."""
    state = store or f"sqlite:{aged_state(tmp_path / 'state.db')}"
    return ["--store", state, "--audit", str(tmp_path / "audit.db"), *extra]


def scrape(port: int) -> str:
    try:
        return httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=5).text
    except httpx.HTTPError:
        return ""


@pytest.mark.parametrize("kind", ["udpin-any", "tcpin-host", "udpout-lan", "config"])
def test_a_trusted_endpoint_on_the_network_is_refused_at_start(tmp_path: Path, kind: str) -> None:
    """The router signs whatever a trusted endpoint sends with the vehicle key: one that is
    not loopback or serial stops the start (status 2, one line naming it, nothing opened)
    unless that exact endpoint is acknowledged; an acknowledgement naming no trusted
    network endpoint is refused too."""
    host = host_address() or "0.0.0.0"
    endpoint = {
        "udpin-any": f"udpin:0.0.0.0:{free_udp_port()}",
        "tcpin-host": f"tcpin:{host}:{free_port()}",
        "udpout-lan": "udpout:192.0.2.77:14550",
        "config": f"udpin:0.0.0.0:{free_udp_port()}",
    }[kind]
    args = ["--vehicle", f"udpout:127.0.0.1:{free_udp_port()}", "--trusted", endpoint]
    said = f"--trusted {endpoint}: not loopback or a serial device"
    if kind == "config":  # an acknowledgement with a typo acknowledges nothing
        config = tmp_path / "router.yaml"
        config.write_text(f"mavlink:\n  trust_network: ['{endpoint}x']\n")
        args += ["--config", str(config)]
        said = f"--trust-network {endpoint}x: is not a --trusted endpoint"
    done = run_router(tmp_path, args)
    assert (done.returncode, done.stdout) == (2, ""), done.stderr
    (line,) = done.stderr.splitlines()
    assert line.startswith(f"antireplay: error: {said}"), line
    assert f"--trust-network {endpoint}" in line or kind == "config"
    assert not (tmp_path / "audit.db").exists()


def test_a_trusted_name_is_resolved_and_every_address_must_be_loopback(tmp_path: Path) -> None:
    """``localhost`` mapped to a LAN address (an /etc/hosts in a container, a resolver
    fallback) is not local: the router resolves the name and stops (status 2) naming the
    endpoint and what it resolved to; it never binds that address and signs for it.  Run
    in a private mount namespace (unshare) with its own /etc/hosts."""
    host = host_address() or "192.0.2.2"
    hosts = tmp_path / "hosts"
    hosts.write_text(f"{host} localhost\n")
    endpoint = f"udpin:localhost:{free_udp_port()}"
    inner = " ".join(
        shlex.quote(a)
        for a in [sys.executable, "-m", "antireplay", "mavlink-router", "--passphrase-env",
                  "MAV_PASSPHRASE", "--store", "memory", "--audit", str(tmp_path / "audit.db"),
                  "--vehicle", f"udpout:127.0.0.1:{free_udp_port()}", "--trusted", endpoint]
    )  # fmt: skip
    done = subprocess.run(
        ["unshare", "-rm", "sh", "-c", f"mount --bind {hosts} /etc/hosts && exec {inner}"],
        capture_output=True, text=True, timeout=60, check=False,
        env={**os.environ, "MAV_PASSPHRASE": "correct-horse-battery-staple"},
    )  # fmt: skip
    assert (done.returncode, done.stdout) == (2, ""), done.stderr
    (line,) = done.stderr.splitlines()
    assert line.startswith(
        f"antireplay: error: --trusted {endpoint}: not loopback or a serial device "
        f"(localhost resolves to {host})"
    ), line
    assert not (tmp_path / "audit.db").exists()


def run_router(tmp_path: Path, args: list[str]) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "MAV_PASSPHRASE": "correct-horse-battery-staple"}
    return subprocess.run(
        [sys.executable, "-m", "antireplay", "mavlink-router", "--passphrase-env",
         "MAV_PASSPHRASE", "--store", "memory", "--audit", str(tmp_path / "audit.db"), *args],
        capture_output=True, text=True, timeout=60, check=False, env=env,
    )  # fmt: skip


def test_an_acknowledged_network_endpoint_is_said_at_start_and_in_the_metrics(
    tmp_path: Path,
) -> None:
    """``--trust-network`` that exact endpoint: the router starts, its start line says the
    endpoint is trusted on the network, the metric counts it, and a frame a host on the
    network sends there reaches the vehicle signed on its behalf (what was acknowledged)."""
    vehicle, metrics = udp_socket(), free_port()
    trusted = f"udpin:0.0.0.0:{free_udp_port()}"
    args = router_args(
        tmp_path, "--vehicle", f"udpout:127.0.0.1:{vehicle.getsockname()[1]}",
        "--trusted", trusted, "--trust-network", trusted, "--metrics-port", str(metrics),
    )  # fmt: skip
    with router_process(args) as run:
        assert f"trusted on the network, acknowledged (--trust-network): {trusted}" in run.line, (
            run.line
        )
        until("the metrics", lambda: "network_trusted_endpoints 1.0" in scrape(metrics))
        lan = udp_socket(host_address() or "127.0.0.1")
        lan.sendto(unsigned_heartbeat(250), ("127.0.0.1", int(trusted.rpartition(":")[2])))
        (frame, _), *_ = frames_from(vehicle, 0, "the heartbeat, signed on its behalf")
        assert frame.signed and frame.link_id == 251


def test_a_stations_ids_claimed_from_another_link_move_no_route(tmp_path: Path) -> None:
    """The finding: a host on the (acknowledged) trusted endpoint sends an unsigned
    HEARTBEAT claiming 255/190, the ids an authenticated ground station uses.  Refused and
    counted (``SOURCE_BOUND``, on the record): the vehicle's COMMAND_ACK to 255/190 still
    goes to the genuine station, none to the attacker."""
    vehicle, gcs, metrics = udp_socket(), udp_socket(), free_port()
    ground, trusted = free_udp_port(), f"udpin:0.0.0.0:{free_udp_port()}"
    args = router_args(
        tmp_path, "--vehicle", f"udpout:127.0.0.1:{vehicle.getsockname()[1]}",
        "--ground", f"udpin:127.0.0.1:{ground}", "--trusted", trusted,
        "--trust-network", trusted, "--metrics-port", str(metrics),
    )  # fmt: skip
    with router_process(args) as run:
        mav, sink = station()
        mav.heartbeat_send(6, 8, 0, 0, 0)
        gcs.sendto(sink.frames[-1], ("127.0.0.1", ground))
        *_, (_, router_side) = frames_from(vehicle, 0, "the station's heartbeat")
        attacker = udp_socket(host_address() or "127.0.0.1")
        attacker.sendto(
            unsigned_heartbeat(255, 190), ("127.0.0.1", int(trusted.rpartition(":")[2]))
        )
        until("the spoof refused", lambda: 'code="SOURCE_BOUND"' in scrape(metrics))
        autopilot, out = station(1, 1)
        autopilot.command_ack_send(400, 0, 0, 0, 255, 190)
        vehicle.sendto(out.frames[-1], router_side)
        frames_from(gcs, 77, "the vehicle's COMMAND_ACK at the genuine station")
        assert 77 not in [frame.msgid for frame in drained(attacker)]
    assert "SOURCE_BOUND" in run.stderr and "claiming 255/190" in run.stderr, run.stderr


def test_a_clock_spike_does_not_fence_a_restart_after_its_moment(tmp_path: Path) -> None:
    """The finding: ``--max-forward-s 20``, one ground frame accepted 17 s ahead; the
    router's clock then passes that moment (stepped 30 s), a clean stop and a restart: the
    start line says no fence, and an honest station's first frame reaches the vehicle."""
    vehicle, gcs, ground = udp_socket(), udp_socket(), free_udp_port()
    args = router_args(
        tmp_path, "--vehicle", f"udpout:127.0.0.1:{vehicle.getsockname()[1]}",
        "--ground", f"udpin:127.0.0.1:{ground}", "--max-forward-s", "20",
    )  # fmt: skip
    with router_process(args, tmp=tmp_path, clock_ahead_s=0) as run:
        mav, sink = station(ahead_s=17)
        mav.heartbeat_send(6, 8, 0, 0, 0)
        gcs.sendto(sink.frames[-1], ("127.0.0.1", ground))
        frames_from(vehicle, 0, "the frame stamped 17 s ahead, accepted")
        run.step_clock(30)  # long after that moment
    with router_process(args, tmp=tmp_path, clock_ahead_s=30) as again:
        assert "fenced" not in again.line, again.line
        mav, sink = station(link_id=2, ahead_s=30)  # honest: stamps the router's clock
        mav.heartbeat_send(6, 8, 0, 0, 0)
        gcs.sendto(sink.frames[-1], ("127.0.0.1", ground))
        frames_from(vehicle, 0, "the honest station's first frame")
    assert "MESSAGE_STALE" not in again.stderr, again.stderr


def test_a_fenced_router_says_until_when_and_why_once(tmp_path: Path) -> None:
    """``--store memory``: the start line says the router is fenced, until when, why and what
    removes it; 200 frames behind the fence are on the log in at most 3 lines; readiness is
    0 while fenced, 1 after."""
    ground, metrics, gcs = free_udp_port(), free_port(), udp_socket()
    args = router_args(
        tmp_path, "--vehicle", f"udpout:127.0.0.1:{free_udp_port()}",
        "--ground", f"udpin:127.0.0.1:{ground}", "--max-forward-s", "8",
        "--metrics-port", str(metrics), store="memory",
    )  # fmt: skip
    ready = 'antireplay_ready{command="mavlink-router"}'
    with router_process(args) as run:
        assert "; fenced until " in run.line and "s more): a memory store starts" in run.line
        assert "--store sqlite:PATH" in run.line, run.line
        until("the metrics", lambda: ready in scrape(metrics))
        assert f"{ready} 0.0" in scrape(metrics)
        senders = [station(sysid) for sysid in (250, 251)]
        for i in range(200):
            mav, sink = senders[i % 2]
            mav.heartbeat_send(6, 8, 0, 0, 0)
            gcs.sendto(sink.frames[-1], ("127.0.0.1", ground))
        until(
            "200 refusals counted",
            lambda: (
                'code="MESSAGE_STALE",direction="inbound"} 200.0' in scrape(metrics)
                or 'direction="inbound",code="MESSAGE_STALE"} 200.0' in scrape(metrics)
            ),
        )
        until("the fence passed", lambda: f"{ready} 1.0" in scrape(metrics))
    lines = [line for line in run.stderr.splitlines() if " refused " in line]
    assert 1 <= len(lines) <= 3, run.stderr
    assert "restart fence" in lines[0] and "summarised every 5 s" in lines[0]
    assert "from 2 senders" in lines[-1], lines
