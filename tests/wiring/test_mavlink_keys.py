"""``signing.keys`` records and provisioning driven step by step: a rotation the vehicle took
but never confirmed leaves the old record and a pending one; a retry with that key confirms;
every write is atomic, through a symlink to its target, keeping owner and group."""

from __future__ import annotations

import os
import stat
import threading
from pathlib import Path

import pytest

from antireplay.mavlink import passphrase_key
from antireplay.mavlink.sim import SimVehicle
from antireplay.wiring.mavlink import read_signing_keys
from antireplay.wiring.mavlink_keys import Provisioned, provision, write_record
from harness import free_udp_port, until


def test_a_record_replaces_its_own_line_and_keeps_the_others(tmp_path: Path) -> None:
    keys = tmp_path / "signing.keys"
    keys.write_text("udpout:127.0.0.1:14550 station\nsysid:1 old\n# a note MAVProxy skips\n")
    write_record(keys, "sysid:1", "new")
    assert keys.read_text().splitlines() == [
        "udpout:127.0.0.1:14550 station", "# a note MAVProxy skips", "sysid:1 new",
    ]  # fmt: skip
    assert stat.S_IMODE(keys.stat().st_mode) == 0o600
    assert read_signing_keys(keys) == {"udpout:127.0.0.1:14550": "station", "sysid:1": "new"}
    assert [p.name for p in tmp_path.iterdir()] == ["signing.keys"]  # no temporary left


def _attempt(port: int, keys: Path, timeout_s: float) -> tuple[threading.Thread, list[Provisioned]]:
    done: list[Provisioned] = []
    link = f"udpin:127.0.0.1:{port}"
    thread = threading.Thread(
        target=lambda: done.append(provision(link, keys, "new-one", timeout_s=timeout_s))
    )
    thread.start()
    return thread, done


def test_an_unconfirmed_rotation_keeps_the_old_record_and_a_retry_confirms(
    tmp_path: Path,
) -> None:
    port, keys = free_udp_port(), tmp_path / "signing.keys"
    write_record(keys, "sysid:1", "old-one")
    sim = SimVehicle(passphrase_key("old-one"), udp=("127.0.0.1", port))
    try:
        thread, done = _attempt(port, keys, timeout_s=5.0)

        def took_the_new_key() -> bool:  # its SETUP_SIGNING was signed with the old key
            sim.telemetry()
            sim.poll(0.05)
            return sim.key == passphrase_key("new-one")

        until("the vehicle takes the new key", took_the_new_key)
        thread.join()  # the vehicle never says so: no HEARTBEAT signed with the new key
        (first,) = done
        assert not first.enabled and first.sent
        assert "no fresh HEARTBEAT signed with the new key" in first.reason
        recorded = read_signing_keys(keys)
        assert recorded["sysid:1"] == "old-one"  # the old key stays in use
        assert recorded["sysid:1:pending"] == "new-one"  # and the one the vehicle may use

        thread, done = _attempt(port, keys, timeout_s=30.0)

        def confirmed() -> bool:
            sim.telemetry()  # signed with the new key now
            sim.poll(0.05)
            return bool(done)

        until("the retry confirms", confirmed)
        thread.join()
        assert done[0].enabled and done[0].rotated
        assert read_signing_keys(keys) == {"sysid:1": "new-one"}  # the pending one gone

        def took_the_retry() -> bool:
            # The retry's SETUP_SIGNING went out before anything could confirm it, but the
            # vehicle signed with the new key already, so a HEARTBEAT it sent before reading
            # that SETUP_SIGNING may have confirmed the retry: it waits in the socket.
            sim.poll(0.05)
            return sim.counts["setup_signing"] == 2

        until("the vehicle takes the retry's SETUP_SIGNING", took_the_retry)
        assert sim.key == passphrase_key("new-one")  # it was signed with the new key
    finally:
        sim.close()


def test_a_symlinked_file_is_updated_in_its_target_keeping_owner_and_group(
    tmp_path: Path,
) -> None:
    """Review 6: the link stays a link, the target gets the record (mode 0600, a warning
    for its old 0644), its owner and group kept."""
    (tmp_path / "etc").mkdir()
    real = tmp_path / "etc" / "real.keys"
    real.write_text("sysid:1 old\n")
    real.chmod(0o644)
    os.chown(real, 65534, 65534)  # nobody (the tests run as root)
    link = tmp_path / "signing.keys"
    link.symlink_to(real)
    warnings = write_record(link, "SYSID:1", "new")
    assert link.is_symlink() and real.read_text() == "SYSID:1 new\n"  # review 10: case
    after = real.stat()
    assert (after.st_uid, after.st_gid, stat.S_IMODE(after.st_mode)) == (65534, 65534, 0o600)
    assert warnings == [f"{link}: was mode 0644, now 0600"]
    assert sorted(p.name for p in (tmp_path / "etc").iterdir()) == ["real.keys"]


def test_a_failed_write_names_the_file_and_changes_nothing(tmp_path: Path) -> None:
    blocker = tmp_path / "etc"
    blocker.write_text("a file where the directory should be\n")
    with pytest.raises(OSError) as caught:
        write_record(blocker / "signing.keys", "sysid:1", "new")
    assert caught.value.filename == str(blocker / "signing.keys")
    assert blocker.read_text() == "a file where the directory should be\n"
