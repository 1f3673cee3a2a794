"""Wiring: the one place that turns configuration into stores, trails and adapters.

Theory of operation
-------------------
The adapters own transport and process lifetime only: :mod:`antireplay.http` speaks HTTP
on built objects, :mod:`antireplay.cli` parses options, reads one configuration file and
calls in here.  What a configuration turns into is decided here, the same way for every
command: open the leaves (:mod:`.leaves`: the replay store and its anchor, the audit trail
with its retention, spill and free-space floors), load the keys, then build the adapter on
them: the gateway (:mod:`.gateway`), the MAVLink router (:mod:`.mavlink`), the
post-quantum ends (:mod:`.mavlink_pq`), the DDS commands (:mod:`.dds`); refused frames go
on the record through one auditor (:mod:`.refusals`) and :mod:`.metrics` serves any
command's counters to Prometheus.  No core and no adapter receives a configuration object, a store
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
    trail_path,
)
from antireplay.wiring.mavlink import (
    Allowed,
    RouterOptions,
    RouterParts,
    build_mavlink_router,
    open_router,
    stop_router,
)
from antireplay.wiring.mavlink_pq import PqParts, open_pq_end
from antireplay.wiring.metrics import (
    pq_metrics,
    router_metrics,
    serve_metrics,
    serve_router_metrics,
)
from antireplay.wiring.refusals import MAVLINK_AUDIT_PER_S, MavlinkRefusals, mavlink_auditor

__all__ = [
    "ANSWER_SLACK_S",
    "DEMO_KID",
    "MAVLINK_AUDIT_PER_S",
    "Allowed",
    "Guard",
    "MavlinkRefusals",
    "PqParts",
    "RcanGuard",
    "RouterOptions",
    "RouterParts",
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
    "open_pq_end",
    "open_router",
    "open_state",
    "open_trail",
    "pq_metrics",
    "router_metrics",
    "serve_metrics",
    "serve_router_metrics",
    "stop_router",
    "trail_path",
]
