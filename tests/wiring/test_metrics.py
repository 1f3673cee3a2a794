"""Metrics wiring: the router's counters as Prometheus families."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

from antireplay.audit import AuditLog
from antireplay.core.clock import ManualClock
from antireplay.mavlink import Refusal
from antireplay.mavlink.router import RouterStats
from antireplay.wiring import (
    MAVLINK_AUDIT_PER_S,
    mavlink_auditor,
    router_metrics,
)


def test_mavlink_refusals_folded_by_the_rate_limit_are_a_metric(tmp_path: Path) -> None:
    log = AuditLog(tmp_path / "audit.db")
    audit = mavlink_auditor(log, ManualClock())
    flood = int(MAVLINK_AUDIT_PER_S) + 7
    for _ in range(flood):
        audit(Refusal("inbound", "udpin:0.0.0.0:14550", "INVALID_FRAME", "x", b"\xfd"))
    router: Any = SimpleNamespace(stats=RouterStats(), links=[], on_reject=audit)
    folded = {
        sample.labels["class"]: sample.value
        for family in router_metrics(router)
        if family.name == "antireplay_mavlink_refusals_rate_limited"
        for sample in family.samples
    }
    assert folded == {"authenticated": 0, "unauthenticated": 7}
    assert log.count() + folded["unauthenticated"] == flood
    log.close()
