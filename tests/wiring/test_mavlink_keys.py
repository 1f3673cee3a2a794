"""``signing.keys`` records and provisioning driven step by step: a rotation the vehicle took
but never confirmed leaves the old record; a retry with the same key confirms at once."""

from __future__ import annotations

import stat
import threading
from pathlib import Path

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
        assert not first.enabled and "no HEARTBEAT signed with the new key" in first.reason
        assert read_signing_keys(keys)["sysid:1"] == "old-one"  # the old key stays in use

        thread, done = _attempt(port, keys, timeout_s=30.0)

        def confirmed() -> bool:
            sim.telemetry()  # signed with the new key now
            sim.poll(0.05)
            return bool(done)

        until("the retry confirms", confirmed)
        thread.join()
        assert done[0].enabled and done[0].rotated
        assert read_signing_keys(keys)["sysid:1"] == "new-one"
        assert sim.counts["setup_signing"] == 1  # the retry sent nothing
    finally:
        sim.close()
