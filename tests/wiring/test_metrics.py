"""Metrics wiring: the router's counters as Prometheus families."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

from antireplay.audit import AuditLog
from antireplay.config import AppConfig
from antireplay.core.clock import ManualClock
from antireplay.mavlink import FrameRefusal
from antireplay.mavlink.router import RouterStats
from antireplay.state.memory import MemoryStore
from antireplay.state.sqlite import SqliteStore
from antireplay.wiring import (
    MAVLINK_AUDIT_PER_S,
    mavlink_auditor,
    open_trail,
    router_metrics,
)
from antireplay.wiring.metrics import leaves_ready, trail_metrics


def test_mavlink_refusals_folded_by_the_rate_limit_are_a_metric(tmp_path: Path) -> None:
    log = AuditLog(tmp_path / "audit.db")
    audit = mavlink_auditor(log, ManualClock())
    flood = int(MAVLINK_AUDIT_PER_S) + 7
    for _ in range(flood):
        audit(FrameRefusal("inbound", "udpin:0.0.0.0:14550", "INVALID_FRAME", "x", b"\xfd"))
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


class DownStore(SqliteStore):
    """A store that cannot take a commit now (SQLite: the compiled MemoryStore takes no
    interpreted subclass)."""

    def ready(self) -> None:
        raise ConnectionError("connection refused")


def test_a_commands_leaves_are_exported_as_the_gateways_are(tmp_path: Path) -> None:
    """Readiness (store, disk, trail) and the trail on disk, for the router and the PQ
    ends as for ``serve``: the same names, labelled with the command."""
    config = AppConfig.from_mapping({"audit": str(tmp_path / "router.db")})
    audit, space = open_trail(config)
    try:
        samples = {
            family.name: family.samples[0]
            for family in trail_metrics("mavlink-router", audit, space, MemoryStore())
        }
        assert samples["antireplay_ready"].value == 1
        assert samples["antireplay_ready"].labels == {"command": "mavlink-router"}
        assert samples["antireplay_audit_trail_segments"].value >= 1
        assert samples["antireplay_audit_free_bytes"].value > 0
        down_store = DownStore(tmp_path / "down.db")
        down = trail_metrics("mavlink-router", audit, space, down_store)
        assert down[0].samples[0].value == 0
        assert leaves_ready(audit, space, down_store) == "store: connection refused"
        down_store.close()
    finally:
        audit.close()
