"""``antireplay mavlink-keys provision`` and the router's SIGHUP reload, on real processes:
a key goes only over a wired link, never to an armed vehicle, and is enabled (recorded in
``signing.keys``) only once the vehicle signs with it; a reload changes the ground keys at
once and a bad file changes nothing."""

from __future__ import annotations

import contextlib
import os
import resource
import signal
import socket
import sqlite3
import stat
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.core.clock import SystemClock
from antireplay.mavlink import mav_time, open_transport, parse_endpoint, passphrase_key
from antireplay.mavlink.sim import SimVehicle
from antireplay.wiring.mavlink import read_signing_keys
from harness import free_port, free_udp_port, until
from harness.mavlink_frames import Sink
from harness.stores import aged_state

CLI = [sys.executable, "-m", "antireplay"]


@contextmanager
def simulated(port: int, *extra: str, env: dict[str, str] | None = None) -> Iterator[list[str]]:
    """``mavlink-sim`` sending to ``127.0.0.1:port``; yields the list its exit line goes in."""
    proc = subprocess.Popen(
        [*CLI, "mavlink-sim", "--udp", f"127.0.0.1:{port}", *extra],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    said: list[str] = []
    try:
        yield said
    finally:
        proc.terminate()
        said.extend(proc.communicate(timeout=30)[1].splitlines())


def provision(
    port: int, keys: Path, *extra: str, env: dict[str, str] | None = None
) -> tuple[int, str, str]:
    done = subprocess.run(
        [*CLI, "mavlink-keys", "provision", f"udpin:127.0.0.1:{port}", "--file", str(keys), *extra],
        capture_output=True, text=True, timeout=120, env=env, check=False,
    )  # fmt: skip
    return done.returncode, done.stdout, done.stderr


def record(keys: Path, system: int = 1) -> str | None:
    for line in keys.read_text().splitlines():
        if line.split()[:1] == [f"sysid:{system}"]:
            return line.split()[1]
    return None


def metrics_text(port: int) -> str:
    try:
        return httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=5).text
    except httpx.HTTPError:
        return ""


def counter(text: str, name: str, labels: str) -> float:
    for line in text.splitlines():
        if line.startswith(f"{name}_total{{") and all(part in line for part in labels.split(",")):
            return float(line.rsplit(" ", 1)[1])
    return 0.0


@contextmanager
def router(
    tmp_path: Path, *args: str, env: dict[str, str] | None = None
) -> Iterator[tuple[subprocess.Popen[str], int, list[str]]]:
    """A real router on an aged SQLite state with metrics; yields it, its metrics port and
    the lines of its stderr so far."""
    metrics = free_port()
    proc = subprocess.Popen(
        [*CLI, "mavlink-router", *args, "--store", f"sqlite:{aged_state(tmp_path / 'state.db')}",
         "--audit", str(tmp_path / "audit.db"), "--metrics-port", str(metrics)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    lines: list[str] = []
    assert proc.stderr is not None and proc.stdout is not None
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stderr.readline, "")))  # type: ignore[union-attr]
    reader.start()
    try:
        assert "mavlink-router" in proc.stdout.readline(), lines
        yield proc, metrics, lines
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        reader.join(timeout=30)


def vehicle_only(port: int, keys: Path) -> list[str]:
    """A router's options: the sim's port as its vehicle, its keys from ``keys`` only."""
    ground = f"udpin:127.0.0.1:{free_udp_port()}"
    return ["--vehicle", f"udpin:127.0.0.1:{port}", "--ground", ground, "--signing-keys", str(keys)]


def test_a_provisioned_key_is_recorded_and_the_router_verifies_the_vehicle_with_it(
    tmp_path: Path,
) -> None:
    """The sim (no key yet) takes SETUP_SIGNING over loopback; the record is written once
    it signs with the key (mode 0600, other lines kept); a router reading only that file
    accepts the sim's frames."""
    port, keys = free_udp_port(), tmp_path / "signing.keys"
    keys.write_text("udp:10.0.0.9:14550 someone-elses\nsysid:2 three words here\n")
    with simulated(port) as sim:
        code, out, err = provision(port, keys)
        assert code == 0, err
        assert f"{keys} line 2: not ENDPOINT PASSPHRASE, skipped" in err, err  # review 10
        assert "key enabled" in out.splitlines()[-1], out
        assert stat.S_IMODE(keys.stat().st_mode) == 0o600
        assert keys.read_text().splitlines()[0] == "udp:10.0.0.9:14550 someone-elses"
        assert record(keys) is not None
        with router(tmp_path, *vehicle_only(port, keys)) as (_, m, _):
            until("the sim's frames accepted", lambda: 'code="NO_PEER"' in metrics_text(m))
            assert 'code="SIGNATURE_INVALID"' not in metrics_text(m)
    assert any("setup_signing 1" in line for line in sim), sim


@pytest.mark.parametrize("link", ["udpin:192.0.2.1:14550", "tcp:vehicle.example:5760",
                                  "udpin:0.0.0.0:14550"])  # fmt: skip
def test_a_link_that_is_not_wired_is_refused_by_name(tmp_path: Path, link: str) -> None:
    keys = tmp_path / "signing.keys"
    done = subprocess.run(
        [*CLI, "mavlink-keys", "provision", link, "--file", str(keys)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert (done.returncode, done.stdout) == (2, ""), done.stderr
    (line,) = done.stderr.splitlines()
    assert line.startswith(f"antireplay: error: {link}: not a wired link"), line
    assert not keys.exists()


def test_an_armed_vehicle_is_refused_and_nothing_is_written(tmp_path: Path) -> None:
    port, keys = free_udp_port(), tmp_path / "signing.keys"
    with simulated(port, "--armed") as sim:
        code, _, err = provision(port, keys, "--timeout", "20")
    assert code == 1 and "is armed" in err, err
    assert not keys.exists()
    assert not any("setup_signing" in line for line in sim), sim  # never sent


def test_a_vehicle_that_never_signs_with_the_new_key_enables_nothing(tmp_path: Path) -> None:
    """The sim signs with a key the file does not know: the unsigned SETUP_SIGNING is not
    taken, no confirmation comes, the attempt times out and writes nothing."""
    port, keys = free_udp_port(), tmp_path / "signing.keys"
    with simulated(port, "--key", "ab" * 32):
        code, _, err = provision(port, keys, "--timeout", "2")
    assert code == 1, err
    assert "signs with a key that is neither the file's record nor the new key" in err
    assert "nothing sent" in err
    assert not keys.exists()


def test_a_rotation_is_signed_with_the_old_key_and_replaces_it_once_confirmed(
    tmp_path: Path,
) -> None:
    """The vehicle signs with A (provisioned); rotating to B sends SETUP_SIGNING signed with A
    (the sim takes nothing unsigned now) and replaces A's record only once the sim signs
    with B; a router then verifies B and no longer A."""
    port, keys = free_udp_port(), tmp_path / "signing.keys"
    env = {**os.environ, "NEW_PASSPHRASE": "rotated-passphrase"}
    with simulated(port) as sim:
        assert provision(port, keys)[0] == 0
        old = record(keys)
        code, out, err = provision(port, keys, "--passphrase-env", "NEW_PASSPHRASE", env=env)
        assert code == 0 and "key rotated" in out, err
        assert record(keys) == "rotated-passphrase" != old
        assert sum(line.startswith("sysid:1 ") for line in keys.read_text().splitlines()) == 1
        with router(tmp_path, *vehicle_only(port, keys)) as (_, m, _):
            until("the sim's frames accepted", lambda: 'code="NO_PEER"' in metrics_text(m))
    assert any("setup_signing 2" in line for line in sim), sim


def test_a_file_that_cannot_be_written_is_named_before_anything_is_sent(tmp_path: Path) -> None:
    """Review 1: the writability is known before SETUP_SIGNING goes (exit 2, the file named)."""
    port, blocker = free_udp_port(), tmp_path / "etc"
    blocker.write_text("a file where the directory should be\n")
    keys = blocker / "signing.keys"
    with simulated(port) as sim:
        code, _, err = provision(port, keys, "--timeout", "5")
    assert code == 2, err
    (line,) = err.splitlines()
    assert f"{keys}:" in line and "nothing sent" in line, line
    assert not any("setup_signing" in x for x in sim), sim


def test_a_timeout_after_the_send_keeps_the_key_pending_and_a_rerun_finishes(
    tmp_path: Path,
) -> None:
    """Review 1: the vehicle took the key but its confirmation never came: the random
    passphrase is in the file as ``sysid:1:pending``, the message says so, and running the
    same command again ends it (a fresh HEARTBEAT signed with that key)."""
    port, keys = free_udp_port(), tmp_path / "signing.keys"
    sim = SimVehicle(None, udp=("127.0.0.1", port))
    try:
        first = subprocess.Popen(
            [*CLI, "mavlink-keys", "provision", f"udpin:127.0.0.1:{port}", "--file", str(keys),
             "--timeout", "3"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip

        def took_a_key() -> bool:  # one HEARTBEAT at a time until the key is taken
            sim.telemetry()
            sim.poll(0.05)
            return sim.key is not None

        until("the vehicle takes the key", took_a_key)
        _, err = first.communicate(timeout=60)  # no HEARTBEAT from it any more
        assert first.returncode == 1, err
        pending = read_signing_keys(keys)["sysid:1:pending"]
        assert passphrase_key(pending) == sim.key
        assert f"kept in {keys} as sysid:1:pending" in err and "run the same command" in err
        code_out: list[tuple[int, str, str]] = []
        rerun = threading.Thread(target=lambda: code_out.append(provision(port, keys)))
        rerun.start()

        def finished() -> bool:
            sim.telemetry()
            sim.poll(0.05)
            return bool(code_out)

        until("the rerun finishes", finished)
        rerun.join()
        code, out, err = code_out[0]
        assert code == 0 and "resuming" in out and "key enabled" in out, err
        assert read_signing_keys(keys) == {"sysid:1": pending}
    finally:
        sim.close()


def test_in_a_rotation_a_spoofed_disarmed_heartbeat_steers_nothing(tmp_path: Path) -> None:
    """Review 2: the vehicle signs with the recorded key and is armed; a local socket
    claims system 1 disarmed, unsigned, before it: it decides nothing and is sent nothing;
    the vehicle's own (signed, armed) HEARTBEAT refuses; the file is unchanged."""
    port, keys = free_udp_port(), tmp_path / "signing.keys"
    keys.write_text("sysid:1 old-passphrase\n")
    sim = SimVehicle(passphrase_key("old-passphrase"), udp=("127.0.0.1", port), armed=True)
    spoof = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    spoof.settimeout(0.05)
    sink = Sink()
    dialect.MAVLink(sink, srcSystem=1, srcComponent=1).heartbeat_send(
        dialect.MAV_TYPE_QUADROTOR, dialect.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4
    )
    env = {**os.environ, "NEW": "new-passphrase"}
    done: list[tuple[int, str, str]] = []
    got: list[bytes] = []
    try:
        attempt = threading.Thread(
            target=lambda: done.append(provision(port, keys, "--passphrase-env", "NEW", env=env))
        )
        attempt.start()
        for _ in range(40):  # the spoofer alone first (a bounded number of tries)
            spoof.sendto(sink.frames[-1], ("127.0.0.1", port))
            with contextlib.suppress(TimeoutError):
                got.append(spoof.recv(512))

        def ended() -> bool:
            sim.telemetry()
            sim.poll(0.05)
            return bool(done)

        until("the attempt ends", ended)
        attempt.join()
    finally:
        sim.close()
        spoof.close()
    code, _, err = done[0]
    assert code == 1 and "is armed" in err, err
    assert got == [] and sim.counts.get("setup_signing", 0) == 0
    assert keys.read_text() == "sysid:1 old-passphrase\n"


class Gcs:
    """A ground station on a UDP socket signing HEARTBEATs with a passphrase's key."""

    def __init__(self, to: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.to = ("127.0.0.1", to)

    def beat(self, passphrase: str) -> None:
        sink = Sink()
        mav = dialect.MAVLink(sink, srcSystem=255, srcComponent=190)
        mav.signing.secret_key, mav.signing.sign_outgoing = passphrase_key(passphrase), True
        mav.signing.link_id = 1
        mav.signing.timestamp = mav_time(SystemClock())
        mav.heartbeat_send(dialect.MAV_TYPE_GCS, dialect.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        self.sock.sendto(sink.frames[-1], self.to)

    @staticmethod
    def counts(metrics: int) -> tuple[float, float]:
        """Frames forwarded towards the vehicle, and refused for their signature."""
        text = metrics_text(metrics)
        forwarded = counter(text, "antireplay_mavlink_forwarded", 'direction="inbound"')
        return forwarded, counter(text, "antireplay_mavlink_dropped", 'code="SIGNATURE_INVALID"')

    def judged(self, metrics: int, passphrase: str) -> str:
        """Send one HEARTBEAT until the router counts it: ``accepted`` or ``refused``."""
        before = self.counts(metrics)
        seen: list[str] = []

        def counted() -> bool:
            self.beat(passphrase)
            now = self.counts(metrics)
            if now[0] > before[0]:
                seen.append("accepted")
            elif now[1] > before[1]:
                seen.append("refused")
            return bool(seen)

        until(f"a HEARTBEAT signed with {passphrase} counted", counted)
        return seen[0]


def test_sighup_reloads_the_ground_keys_and_a_bad_file_keeps_them(tmp_path: Path) -> None:
    ground = free_udp_port()
    keys = tmp_path / "signing.keys"
    keys.write_text(f"udpin:127.0.0.1:{ground} gcs-one\n")
    env = {**os.environ, "MAV_PASSPHRASE": "vehicle-passphrase"}
    args = ["--vehicle", f"udpin:127.0.0.1:{free_udp_port()}", "--ground",
            f"udpin:127.0.0.1:{ground}", "--signing-keys", str(keys),
            "--passphrase-env", "MAV_PASSPHRASE"]  # fmt: skip
    with router(tmp_path, *args, env=env) as (proc, metrics, lines):
        gcs = Gcs(ground)
        assert gcs.judged(metrics, "gcs-one") == "accepted"
        keys.write_text(f"udpin:127.0.0.1:{ground} gcs-two\n")
        proc.send_signal(signal.SIGHUP)
        until("the reload logged", lambda: any("signing keys reloaded" in x for x in lines))
        assert gcs.judged(metrics, "gcs-one") == "refused"  # the removed key, at once
        assert gcs.judged(metrics, "gcs-two") == "accepted"  # the new one
        keys.write_bytes(b"\xff\xfe not a text file\n")
        proc.send_signal(signal.SIGHUP)
        until("the bad file logged", lambda: any("not reloaded" in x for x in lines))
        assert gcs.judged(metrics, "gcs-two") == "accepted"  # the old keys stay
        assert proc.poll() is None
        keys.write_text("")  # its line gone: the link falls back to the default key
        proc.send_signal(signal.SIGHUP)
        until("the removal logged", lambda: sum("signing keys reloaded" in x for x in lines) == 2)
        assert gcs.judged(metrics, "gcs-two") == "refused"
        assert gcs.judged(metrics, "vehicle-passphrase") == "accepted"
    assert sum("not reloaded" in line for line in lines) == 1, lines


def _rows(db: Path, like: str) -> int:
    with sqlite3.connect(db) as conn:
        return int(
            conn.execute("select count(*) from counters where key like ?", (like,)).fetchone()[0]
        )


def test_reloads_of_a_link_left_keyless_keep_one_guard(tmp_path: Path) -> None:
    """Review 7: a ground line removed with no default key: the first SIGHUP moves the link
    to the one key nobody holds; 19 more change nothing and add no guard, signer or lease."""
    vehicle, ground = free_udp_port(), free_udp_port()
    keys = tmp_path / "signing.keys"
    keys.write_text(f"udpin:127.0.0.1:{vehicle} vehicle-pass\nudpin:127.0.0.1:{ground} gcs\n")
    args = ["--vehicle", f"udpin:127.0.0.1:{vehicle}", "--ground", f"udpin:127.0.0.1:{ground}",
            "--signing-keys", str(keys)]  # fmt: skip
    with router(tmp_path, *args) as (proc, _, lines):
        keys.write_text(f"udpin:127.0.0.1:{vehicle} vehicle-pass\n")
        proc.send_signal(signal.SIGHUP)
        until("the first reload", lambda: any("reloaded" in x for x in lines))
        assert any(f"udpin:127.0.0.1:{ground} changed" in x for x in lines), lines
        db = tmp_path / "state.db"
        until("the keyless guard stored", lambda: _rows(db, "mav-in-%lease%") > 0)
        after_one = _rows(db, "mav-%")

        def reloaded(count: int) -> Callable[[], bool]:
            return lambda: sum("reloaded" in x for x in lines) >= count

        for count in range(2, 21):
            proc.send_signal(signal.SIGHUP)
            until(f"reload {count}", reloaded(count))
        assert sum("no link changed" in x for x in lines) == 19, lines
        assert _rows(db, "mav-%") == after_one
        assert proc.poll() is None


def test_a_sighup_during_start_up_reloads_and_never_kills(tmp_path: Path) -> None:
    """Review 8: a router waiting out a killed run's lease (its metrics already served) is
    sent SIGHUP: it reloads, then starts."""
    vehicle = free_udp_port()
    keys = tmp_path / "signing.keys"
    keys.write_text(f"udpin:127.0.0.1:{vehicle} vehicle-pass\n")
    args = ["--vehicle", f"udpin:127.0.0.1:{vehicle}", "--signing-keys", str(keys)]
    with router(tmp_path, *args) as (crashed, _, _):
        crashed.kill()  # its lease stays held until it expires
        crashed.wait(timeout=30)
    metrics = free_port()
    proc = subprocess.Popen(
        [*CLI, "mavlink-router", *args, "--store", f"sqlite:{tmp_path / 'state.db'}",
         "--audit", str(tmp_path / "audit2.db"), "--metrics-port", str(metrics)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        until("metrics served (start-up under way)", lambda: bool(metrics_text(metrics)))
        proc.send_signal(signal.SIGHUP)
        assert proc.stdout is not None
        assert "mavlink-router" in proc.stdout.readline()
        assert proc.poll() is None
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0 and "signing keys reloaded" in err, err


def test_a_changed_vehicle_record_moves_no_link_and_says_restart(tmp_path: Path) -> None:
    """Review 4: a rotation rewrote ``sysid:1``; SIGHUP keeps the vehicle and the ground
    links on the key they started with (ground frames signed with it still pass) and
    says to restart."""
    ground = free_udp_port()
    keys = tmp_path / "signing.keys"
    keys.write_text("sysid:1 old-vehicle\n")
    args = ["--vehicle", f"udpin:127.0.0.1:{free_udp_port()}", "--ground",
            f"udpin:127.0.0.1:{ground}", "--signing-keys", str(keys)]  # fmt: skip
    with router(tmp_path, *args) as (proc, metrics, lines):
        gcs = Gcs(ground)
        assert gcs.judged(metrics, "old-vehicle") == "accepted"
        keys.write_text("sysid:1 new-vehicle\n")
        proc.send_signal(signal.SIGHUP)
        until("the reload logged", lambda: any("reloaded" in x for x in lines))
        (line,) = [x for x in lines if "reloaded" in x]
        assert "no link changed" in line and "restart the router to use it" in line, line
        assert gcs.judged(metrics, "old-vehicle") == "accepted"


def test_provision_refuses_a_port_the_router_holds(tmp_path: Path) -> None:
    """Review 4: the router's vehicle port is bound: provision says to stop it first,
    sends nothing and leaves the file as it was."""
    vehicle = free_udp_port()
    keys = tmp_path / "signing.keys"
    keys.write_text("sysid:1 vehicle-pass\n")
    with router(tmp_path, *vehicle_only(vehicle, keys)):
        code, _, err = provision(vehicle, keys)
    assert code == 2 and "stop the router using it first" in err and "nothing sent" in err, err
    assert keys.read_text() == "sysid:1 vehicle-pass\n"


def test_add_writes_atomically_and_names_the_file(tmp_path: Path) -> None:
    """Review 5: a write cut short by the file-size limit leaves the file whole (the
    provisioned record kept) and names it."""
    keys = tmp_path / "signing.keys"
    lines = [f"udpout:10.0.0.{i}:14550 groundpass{i}" for i in range(60)]
    keys.write_text("\n".join([*lines, "sysid:1 RANDOMvehiclepassphrase"]) + "\n")
    before = keys.read_text()

    def limited() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (1024, 1024))

    done = subprocess.run(
        [*CLI, "mavlink-keys", "add", "--file", str(keys), "udpout:127.0.0.1:14550"],
        capture_output=True, text=True, timeout=60, check=False, preexec_fn=limited,
        env={**os.environ, "MAV_PASSPHRASE": "newgs"},
    )  # fmt: skip
    assert done.returncode == 2 and str(keys) in done.stderr, done.stderr
    assert keys.read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["signing.keys"]


def test_the_start_line_names_skipped_lines_and_an_overriding_record(tmp_path: Path) -> None:
    """Review 10: a three-word line is named once; a ``sysid:1`` record that overrides
    ``--passphrase-env`` says so in the start line."""
    keys = tmp_path / "signing.keys"
    keys.write_text("sysid:2 three words here\nSYSID:1 vehicle-pass\n")
    args = ["--vehicle", f"udpin:127.0.0.1:{free_udp_port()}", "--signing-keys", str(keys),
            "--passphrase-env", "MAV_PASSPHRASE"]  # fmt: skip
    metrics = free_port()
    proc = subprocess.Popen(
        [*CLI, "mavlink-router", *args, "--store", f"sqlite:{aged_state(tmp_path / 'st.db')}",
         "--audit", str(tmp_path / "audit.db"), "--metrics-port", str(metrics)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "MAV_PASSPHRASE": "flag-pass"},
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    assert f"{keys} line 1: not ENDPOINT PASSPHRASE, skipped" in line, line
    assert f"default key: the sysid:1 record of {keys}, not --passphrase-env" in line, line


def test_provision_refuses_a_serial_device_another_process_holds(tmp_path: Path) -> None:
    """Review 4: a router holds the vehicle's serial device (here its transport, locked as
    the router's is): provision says to stop it, sends nothing, writes nothing."""
    leader, follower = os.openpty()
    device = os.ttyname(follower)
    held = open_transport(parse_endpoint(f"{device},115200"))
    keys = tmp_path / "signing.keys"
    try:
        done = subprocess.run(
            [*CLI, "mavlink-keys", "provision", f"{device},115200", "--file", str(keys)],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
    finally:
        held.close()
        os.close(leader)
        os.close(follower)
    (line,) = done.stderr.splitlines()
    assert done.returncode == 2, line
    assert "held by another process (stop the router using it first); nothing sent" in line
    assert not keys.exists()


def test_a_link_carrying_radio_status_is_refused_as_not_wired(tmp_path: Path) -> None:
    """Review 11: a SiK radio injects RADIO_STATUS: the key would go over the air, so
    nothing is sent and nothing written, and the message says why."""
    port, keys = free_udp_port(), tmp_path / "signing.keys"
    radio = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink = Sink()
    dialect.MAVLink(sink, srcSystem=51, srcComponent=68).radio_status_send(1, 2, 3, 4, 5, 6, 7)
    done: list[tuple[int, str, str]] = []
    attempt = threading.Thread(target=lambda: done.append(provision(port, keys)))
    attempt.start()

    def refused() -> bool:
        radio.sendto(sink.frames[-1], ("127.0.0.1", port))
        return bool(done)

    try:
        until("the attempt ends", refused)
        attempt.join()
    finally:
        radio.close()
    code, _, err = done[0]
    assert code == 1 and "RADIO_STATUS heard" in err and "nothing sent" in err, err
    assert not keys.exists()


def _sigint_at_its_default() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_after_the_send_keeps_the_key_pending(tmp_path: Path) -> None:
    """Review 1: SIGINT once the vehicle took the key: exit 1, "interrupted", the passphrase
    the vehicle now uses kept as ``sysid:1:pending`` and the message says where."""
    port, keys = free_udp_port(), tmp_path / "signing.keys"
    sim = SimVehicle(None, udp=("127.0.0.1", port))
    try:
        # Ctrl-C as at a terminal: SIGINT at its default in the child whatever this run
        # inherited (a job started in the background by a non-interactive shell ignores
        # SIGINT, its children too, and a Python started so never raises KeyboardInterrupt).
        proc = subprocess.Popen(
            [*CLI, "mavlink-keys", "provision", f"udpin:127.0.0.1:{port}", "--file", str(keys),
             "--timeout", "120"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            preexec_fn=_sigint_at_its_default,  # noqa: PLW1509 - one sigaction, no lock
        )  # fmt: skip

        def took_a_key() -> bool:
            sim.telemetry()
            sim.poll(0.05)
            return sim.key is not None

        until("the vehicle takes the key", took_a_key)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        sim.close()
    assert proc.returncode == 1 and "interrupted" in err, err
    assert f"kept in {keys} as sysid:1:pending" in err, err
    assert passphrase_key(read_signing_keys(keys)["sysid:1:pending"]) == sim.key
