"""The router wiring: guards per key and direction, endpoints, refusals on the record."""

from __future__ import annotations

import logging
import re
import socket
import time
from pathlib import Path

import pytest

from antireplay.audit import AuditLog, Retention
from antireplay.config import AppConfig
from antireplay.core.clock import ManualClock, SystemClock
from antireplay.core.errors import ConfigError
from antireplay.mavlink import UNITS_PER_S, FrameRefusal, Role, mav_time, passphrase_key
from antireplay.state.memory import MemoryStore
from antireplay.state.sqlite import SqliteStore
from antireplay.wiring import (
    MAVLINK_AUDIT_PER_S,
    Allowed,
    MavlinkRefusals,
    RouterOptions,
    build_mavlink_router,
    mavlink_auditor,
    open_router,
    stop_router,
)
from antireplay.wiring.mavlink import fence_notice
from harness import free_port
from harness.mavlink_frames import KEY


def test_mavlink_rejections_are_audited_with_the_claimed_source_rate_limited(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    log = AuditLog(tmp_path / "audit.db")
    clock = ManualClock()
    audit = mavlink_auditor(log, clock)
    frame = bytes([0xFD, 9, 0, 0, 0, 255, 190]) + bytes(14)
    for _ in range(int(MAVLINK_AUDIT_PER_S) + 10):
        audit(FrameRefusal("inbound", "udpin:0.0.0.0:14550", "INVALID_FRAME", "x", frame))
    clock.advance(2 / MAVLINK_AUDIT_PER_S)  # a token back (and a spare for rounding)
    with caplog.at_level(logging.WARNING, logger="antireplay.mavlink"):
        audit(FrameRefusal("outbound", "/dev/ttyACM0,57600", "INVALID_FRAME", "x", b"\xfd\x00"))
    records = log.tail(1_000)
    log.close()
    assert len(records) == MAVLINK_AUDIT_PER_S + 1
    first, last = records[0], records[-1]
    assert first.at == clock.wall() - 2 / MAVLINK_AUDIT_PER_S
    assert (first.sender, first.sender_verified, first.code) == (
        "mav:inbound:255/190",
        False,
        "INVALID_FRAME",
    )
    assert (first.outcome, first.warning) == ("rejected", None)
    assert (last.sender, last.warning) == ("mav:outbound", None)
    assert caplog.messages[-1] == (
        "refused outbound frame on /dev/ttyACM0,57600: INVALID_FRAME: x "
        "(10 more refusals not logged)"
    )


def test_mavlink_router_guards_per_key_and_direction(tmp_path: Path) -> None:
    log = AuditLog(tmp_path / "audit.db")
    vehicle_key, radio_key = bytes(32), passphrase_key("radio link")
    options = RouterOptions(
        system_id=7, to_vehicle=Allowed(frozenset({0, 109}), frozenset({109})),
        from_vehicle=Allowed(frozenset({109})), reorder_window=16, write_through=True,
        max_forward_s=5.0, new_stream_max_age_s=300.0,
    )  # fmt: skip
    router = build_mavlink_router(
        [
            (Role.VEHICLE, "udpout:127.0.0.1:9", vehicle_key),
            (Role.GROUND, "udpin:127.0.0.1:0", vehicle_key),
            (Role.GROUND, "udp:127.0.0.1:0", radio_key),
            (Role.TRUSTED, "udpin:127.0.0.1:0", None),
        ],
        MemoryStore(),
        log,
        options,
    )
    try:
        inbound, radio, outbound = (
            router.inbound[vehicle_key],
            router.inbound[radio_key],
            router.outbound,
        )
        assert inbound.prefix == "mav-in" and outbound.prefix == "mav-out"
        assert radio.prefix.startswith("mav-in-") and radio_key.hex()[:8] not in radio.prefix
        assert (inbound.system_id, radio.system_id, outbound.system_id) == (7, 7, None)
        assert inbound.allow_unsigned == frozenset({0, 109}) and inbound.allow_v1 == frozenset(
            {109}
        )
        assert outbound.allow_unsigned == frozenset({109}) and outbound.allow_v1 == frozenset()
        for guard in (inbound, radio, outbound):
            assert guard.reorder_window == 16 and guard.write_through
            assert guard.max_forward == 5 * 100_000 and guard.new_stream_max_age == 300 * 100_000
        assert set(router.signers) == {vehicle_key, radio_key}
        assert [link.role for link in router.links] == [
            Role.VEHICLE, Role.GROUND, Role.GROUND, Role.TRUSTED,
        ]  # fmt: skip
    finally:
        for link in router.links:
            link.transport.close()
        log.close()


def test_endpoint_that_is_not_a_serial_port_names_itself_and_closes_the_others(
    tmp_path: Path,
) -> None:
    """``--vehicle /dev/null,115200``: an OSError naming the endpoint (no termios
    traceback), and the ground port opened before it is free again."""
    port = free_port()
    log = AuditLog(tmp_path / "audit.db")
    try:
        with pytest.raises(OSError, match=r"\] /dev/null,115200: not a serial port \("):
            build_mavlink_router(
                [
                    (Role.GROUND, f"tcpin:127.0.0.1:{port}", KEY),
                    (Role.VEHICLE, "/dev/null,115200", KEY),
                ],
                MemoryStore(),
                log,
            )
        socket.create_server(("127.0.0.1", port)).close()  # closed again
    finally:
        log.close()


def test_open_router_builds_on_the_leaves_serve_opens(tmp_path: Path) -> None:
    """The router's store is the ``mavlink.store`` spec, anchored as ``state.anchor`` says;
    its trail is rotated and retained as ``audit:`` says, with the spill and the floors."""
    key = tmp_path / "link.key"
    key.write_bytes(KEY)
    (tmp_path / "anchor").mkdir()
    (tmp_path / "state").mkdir()
    config = AppConfig.from_mapping({
        "state": {"anchor": {"path": str(tmp_path / "anchor" / "mav.anchor")}},
        "audit": {"path": str(tmp_path / "router.db"), "segment_bytes": 1 << 20,
                  "max_bytes": 4 << 20},
        "audit_space": {"min_free_bytes": 1 << 62, "refuse_free_bytes": 0},
        "mavlink": {"vehicle": ["udpin:127.0.0.1:0"], "key_file": str(key),
                    "store": f"sqlite:{tmp_path / 'state' / 'mav.db'}"},
    })  # fmt: skip
    parts = open_router(config)
    try:
        assert isinstance(parts.store, SqliteStore) and parts.store.anchor is not None
        assert parts.audit.path == tmp_path / "router.db"
        assert parts.audit.retention == Retention(1 << 20, 86_400, 4 << 20, None)
        assert tmp_path.joinpath("router.db.spill").exists()
        refusals = parts.router.on_reject
        assert isinstance(refusals, MavlinkRefusals) and refusals.auditor.quiet()  # floor
    finally:
        parts.close()


def test_open_router_refuses_an_anchor_beside_a_store_that_is_not_sqlite(tmp_path: Path) -> None:
    config = AppConfig.from_mapping({
        "state": {"anchor": {"path": str(tmp_path / "mav.anchor")}},
        "audit": str(tmp_path / "router.db"),
        "mavlink": {"vehicle": ["udpin:127.0.0.1:0"], "passphrase_env": "PATH",
                    "store": "memory"},
    })  # fmt: skip
    with pytest.raises(ConfigError) as refused:
        open_router(config)
    assert refused.value.key == "state.anchor" and "store memory" in refused.value.allowed


def test_a_restart_inside_a_new_states_first_fence_says_the_state_is_new(
    tmp_path: Path,
) -> None:
    """A new SQLite state fences its first ``max_forward_s``; a clean stop and a restart
    inside it keeps the fence, and the start line says the true reason (the state is new,
    fenced since its first start), not a memory store's text nor "use a persistent store"."""
    options = RouterOptions(max_forward_s=60.0)
    notices = []
    for _ in range(2):
        store, log = SqliteStore(tmp_path / "state.db"), AuditLog(tmp_path / "audit.db")
        router = build_mavlink_router(
            [(Role.VEHICLE, "udpout:127.0.0.1:9", KEY), (Role.GROUND, "udpin:127.0.0.1:0", KEY)],
            store, log, options,
        )  # fmt: skip
        router.start()
        notices.append(fence_notice(router, store, time.time()))
        stop_router(router)
        store.close()
        log.close()
    first, second = notices
    assert first is not None and second is not None
    assert "memory" not in second and "--store sqlite:PATH" not in second, second
    assert ": this sqlite state is new: fenced since its first start" in second, second
    assert "a restart does not shorten it" in second
    assert first.split(" (")[0] == second.split(" (")[0]  # the same moment: fenced until T


def test_a_clock_spikes_fence_says_how_far_ahead_the_frame_was_stamped(tmp_path: Path) -> None:
    """The previous run persisted a highest timestamp 120 s ahead (a spoofed clock): the start
    line says the fence's cause with how far ahead of this clock that frame was stamped."""
    store, log = SqliteStore(tmp_path / "state.db"), AuditLog(tmp_path / "audit.db")
    ahead = mav_time(SystemClock()) + 120 * UNITS_PER_S
    store.advance("mav-in:high", ahead)
    router = build_mavlink_router(
        [(Role.VEHICLE, "udpout:127.0.0.1:9", KEY), (Role.GROUND, "udpin:127.0.0.1:0", KEY)],
        store, log, RouterOptions(max_forward_s=60.0),
    )  # fmt: skip
    try:
        router.start()
        notice = fence_notice(router, store, time.time())
    finally:
        stop_router(router)
        store.close()
        log.close()
    assert notice is not None
    said = re.search(r"accepted a frame stamped ([0-9.]+) s ahead of this clock", notice)
    assert said is not None, notice
    assert 115 <= float(said.group(1)) <= 120, notice
