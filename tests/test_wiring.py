"""The wiring: what a configuration or the proxy's options turn into."""

from __future__ import annotations

from pathlib import Path

from antireplay.audit import AuditLog
from antireplay.clock import ManualClock
from antireplay.errors import InvalidFrameError
from antireplay.stores.memory import MemoryStore
from antireplay.wiring import MAVLINK_AUDIT_PER_S, build_mavlink_proxy, mavlink_auditor


def test_mavlink_rejections_are_audited_with_the_claimed_source_rate_limited(
    tmp_path: Path,
) -> None:
    log = AuditLog(tmp_path / "audit.db")
    clock = ManualClock()
    audit = mavlink_auditor(log, clock)
    frame = bytes([0xFD, 9, 0, 0, 0, 255, 190]) + bytes(14)
    for _ in range(int(MAVLINK_AUDIT_PER_S) + 10):
        audit("inbound", InvalidFrameError("x"), frame)
    clock.advance(2 / MAVLINK_AUDIT_PER_S)  # a token back (and a spare for rounding)
    audit("outbound", InvalidFrameError("x"), b"\xfd\x00")
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


def test_mavlink_proxy_guards_bind_only_inbound_to_the_vehicle(tmp_path: Path) -> None:
    log = AuditLog(tmp_path / "audit.db")
    proxy = build_mavlink_proxy(
        ("127.0.0.1", 0), ("127.0.0.1", 9), bytes(32), MemoryStore(), log, system_id=7,
        allow_unsigned=frozenset({0}), reorder_window=16, write_through=True,
    )  # fmt: skip
    try:
        inbound, outbound = proxy.inbound, proxy.outbound
        assert (inbound.prefix, outbound.prefix) == ("mav-in", "mav-out")
        assert (inbound.system_id, outbound.system_id) == (7, None)
        for guard in (inbound, outbound):
            assert guard.allow_unsigned == frozenset({0}) and guard.reorder_window == 16
            assert guard.write_through and guard.store is inbound.store
    finally:
        proxy.ground.close()
        proxy.vehicle.close()
        log.close()
