"""Wiring: the one place that turns configuration into stores, trails and adapters.

Theory of operation
-------------------
The adapters own transport and process lifetime only: :mod:`antireplay.http` speaks HTTP
on built objects, :mod:`antireplay.cli` parses options, reads one configuration file and
calls in here.  What a configuration turns into is decided here, the same way for every
command: open the leaves (:mod:`.leaves`: the replay store and its anchor, the audit trail
with its retention, spill and free-space floors), load the keys, then build the adapter on
them: the gateway (:mod:`.gateway`), the MAVLink router and the post-quantum ends
(:mod:`.mavlink`), the DDS commands (:mod:`.dds`); :mod:`.metrics` serves any command's
counters to Prometheus.  No core and no adapter receives a configuration object, a store
spec or a path to open.
"""

from __future__ import annotations

from antireplay.wiring.gateway import (
    ANSWER_SLACK_S,
    DEMO_KID,
    Guard,
    RcanGuard,
    build_receiver,
    build_registry,
    create_app,
    embedded_default,
)
from antireplay.wiring.leaves import (
    anchor_summary,
    anchor_warnings,
    build_anchor,
    open_audit,
    open_state,
    open_trail,
)
from antireplay.wiring.mavlink import (
    MAVLINK_AUDIT_PER_S,
    Allowed,
    MavlinkRefusals,
    RouterOptions,
    build_mavlink_router,
    mavlink_auditor,
    stop_router,
)
from antireplay.wiring.metrics import router_metrics, serve_metrics, serve_router_metrics

__all__ = [
    "ANSWER_SLACK_S",
    "DEMO_KID",
    "MAVLINK_AUDIT_PER_S",
    "Allowed",
    "Guard",
    "MavlinkRefusals",
    "RcanGuard",
    "RouterOptions",
    "anchor_summary",
    "anchor_warnings",
    "build_anchor",
    "build_mavlink_router",
    "build_receiver",
    "build_registry",
    "create_app",
    "embedded_default",
    "mavlink_auditor",
    "open_audit",
    "open_state",
    "open_trail",
    "router_metrics",
    "serve_metrics",
    "serve_router_metrics",
    "stop_router",
]
