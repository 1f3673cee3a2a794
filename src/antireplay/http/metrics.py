"""Prometheus metrics of one gateway: counted as requests pass, and read at scrape time.

:class:`Metrics` owns its own registry (so tests, and an app with several guards, can run
several) with the request counters the guard moves after each answer: accepted (with the
warning it carried), rejected by code, store failures, upstream failures, QoS retries
answered with their original answer, and the latency of the receive path.
:class:`StateCollector` reads everything else when Prometheus scrapes: the replay state of
the backend actually in use (entries, watermark, fence, early evictions, data-loss
events), the window's refusals by cause, the group commits of the state and the audit
trail, the ESTOPs delivered while the audit trail failed, and the trail under a flood:
refusals folded, summarised or left unrecorded, bytes, segments, postponed rotations, the
oldest row's age, free space under it and the pressure against its floors.  While the
store is down its gauges are NaN (unknown) and its counters keep their last known value.
A scrape may read the store, so ``GET /metrics`` runs it in a thread.
"""

from __future__ import annotations

import math
import sqlite3
import time
from collections.abc import Iterator
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import Response

from antireplay.audit import AuditLog
from antireplay.audit.segments import TrailUsage
from antireplay.core.errors import StateUnavailableError
from antireplay.http.workers import Door
from antireplay.rcan.receive import Outcome, Receiver
from antireplay.state.groupcommit import GroupCommitter

#: Latency buckets from 50 µs (a check takes ~0.1 ms; an fsync a few ms) to 2.5 s.
LATENCY_BUCKETS = (
    0.00005, 0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5,
    1.0, 2.5, float("inf"),
)  # fmt: skip


class Metrics:
    """Prometheus metrics of one gateway (its own registry, so tests can run several)."""

    def __init__(self, receiver: Receiver) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.accepted = Counter("antireplay_accepted", "Accepted messages", registry=r)
        self.rejected = Counter("antireplay_rejected", "Rejected messages", ["code"], registry=r)
        self._rejected: dict[str, Any] = {}  # the code's child of ``rejected``
        self.warnings = Counter(
            "antireplay_warnings", "Accepted with warning", ["warning"], registry=r
        )
        self.latency = Histogram(
            "antireplay_latency_seconds", "Pipeline latency", buckets=LATENCY_BUCKETS, registry=r
        )
        self.store_errors = Counter(
            "antireplay_store_errors", "STATE_UNAVAILABLE answers", registry=r
        )
        self.upstream_errors = Counter(
            "antireplay_upstream_errors", "Upstream failures", registry=r
        )
        self.retries = Counter(
            "antireplay_retries_answered", "QoS retries given the original answer", registry=r
        )
        r.register(StateCollector(receiver))
        #: The ESTOP doors of the guards counting here (:class:`~.workers.Door`).
        self.doors: list[Door] = []
        r.register(DoorCollector(self.doors))

    def watch(self, door: Door) -> None:
        """Count ``door``'s waits, holds and copies here too."""
        self.doors.append(door)

    async def endpoint(self, _: Request) -> Response:
        """``GET /metrics`` (a Starlette endpoint: ``app.add_route("/metrics", ...)``)."""
        body = await run_in_threadpool(generate_latest, self.registry)  # may read the store
        return Response(body, media_type="text/plain; version=0.0.4")

    def observe(self, outcome: Outcome, seconds: float) -> None:
        self.latency.observe(seconds)
        if outcome.accepted:
            self.accepted.inc()
            if outcome.warning:
                self.warnings.labels(outcome.warning).inc()
        else:
            code = outcome.code or "UNKNOWN"
            child = self._rejected.get(code)
            if child is None:  # a label's child found once, not per refusal
                child = self._rejected[code] = self.rejected.labels(code)
            child.inc()
            if outcome.code == "STATE_UNAVAILABLE":
                self.store_errors.inc()
            if outcome.retry is not None:
                self.retries.inc()


class DoorCollector(Collector):
    """The ESTOP doors: requests that waited at one, holds taken, ESTOP copies that took none."""

    def __init__(self, doors: list[Door]) -> None:
        self.doors = doors

    def collect(self) -> Iterator[Metric]:
        for name, doc, attr in (
            ("antireplay_door_waits", "Requests that waited at a door an ESTOP held", "waited"),
            ("antireplay_door_holds", "Doors held by an authenticated ESTOP (one per msg_id)",
             "holds"),
            ("antireplay_estop_copies", "ESTOP copies delivered holding no door", "copies"),
        ):  # fmt: skip
            counter = CounterMetricFamily(name, doc)
            counter.add_metric([], sum(getattr(door, attr) for door in self.doors))
            yield counter


class StateCollector(Collector):
    """The replay state of the backend actually in use, read at scrape time.  While the
    store is down its gauges are NaN (unknown) and its counters keep their last known
    value (a counter is never NaN: a rate over it would be NaN too); none known, no sample."""

    def __init__(self, receiver: Receiver) -> None:
        self.receiver = receiver
        self._counted: dict[str, float] = {}

    def collect(self) -> Iterator[Metric]:
        cache = self.receiver.cache
        try:
            status = cache.store.status()
        except StateUnavailableError:
            status = {}
        backend = cache.store.backend
        for name, doc, key in (
            ("antireplay_cache_entries", "Entries in the seen-set", "entries"),
            ("antireplay_state_watermark_seconds", "Largest expiry forgotten", "watermark"),
            ("antireplay_state_fence_seconds", "Restart/data-loss fence", "fence"),
        ):
            gauge = GaugeMetricFamily(name, doc, labels=["backend"])
            gauge.add_metric([backend], status.get(key, float("nan")))
            yield gauge
        for name, doc, key in (
            ("antireplay_watermark_raises_total", "Entries evicted early (full)", "evictions"),
            ("antireplay_state_data_loss_total", "Data-loss events noticed", "data_loss_events"),
            (
                "antireplay_state_no_history_total",
                "Starts fenced: state with no history",
                "no_history_events",
            ),
            (
                "antireplay_state_witness_failures_total",
                "Witness writes failed after a COMMIT",
                "witness_failures",
            ),
        ):
            counter = CounterMetricFamily(name, doc, labels=["backend"])
            if key in status:
                self._counted[key] = status[key]
            if key in self._counted:
                counter.add_metric([backend], self._counted[key])
            yield counter
        refusals = CounterMetricFamily(
            "antireplay_replay_refusals", "Window refusals by cause", labels=["cause"]
        )
        for cause, count in sorted(cache.refusals.items()):
            refusals.add_metric([cause], count)
        yield refusals
        fence = CounterMetricFamily(
            "antireplay_restart_fence_rejections_total", "Refused by the restart/data-loss fence"
        )
        fence.add_metric([], cache.refusals["restart_fence"])
        yield fence
        batches = CounterMetricFamily(
            "antireplay_group_commit_batches", "Durable commits (one fsync each)", labels=["log"]
        )
        operations = CounterMetricFamily(
            "antireplay_group_commit_operations", "Records in those commits", labels=["log"]
        )
        for name, owner in (("state", cache.store), ("audit", self.receiver.audit)):
            committer = getattr(owner, "group_commit", None)
            if isinstance(committer, GroupCommitter):
                batches.add_metric([name], committer.batches)
                operations.add_metric([name], committer.operations)
        yield batches
        yield operations
        stats = self.receiver.stats
        held = CounterMetricFamily(
            "antireplay_estops_unaudited", "ESTOPs delivered while the audit trail failed"
        )
        held.add_metric([], stats.held_estops)
        yield held
        dropped = CounterMetricFamily(
            "antireplay_audit_held_dropped", "Held ESTOP audit rows dropped (bound reached)"
        )
        dropped.add_metric([], stats.held_dropped)
        yield dropped
        waiting = GaugeMetricFamily(
            "antireplay_audit_held_rows", "ESTOP audit rows held until the trail is writable"
        )
        waiting.add_metric([], self.receiver.held_rows)
        yield waiting
        yield from self._trail()

    def _trail(self) -> Iterator[Metric]:
        """The audit trail under a flood: refusals folded and summarised, what it holds on
        disk, the free space under it and the pressure level (0 ok, 1 low, 2 critical)."""
        receiver, auditor = self.receiver, self.receiver.refusals
        folded = CounterMetricFamily(
            "antireplay_audit_refusals_folded", "Refusals given no row of their own",
            labels=["class"],
        )  # fmt: skip
        for cls in ("authenticated", "unauthenticated"):
            folded.add_metric([cls], auditor.folded[cls])
        yield folded
        for name, doc, value in (
            ("antireplay_audit_refusals_summarised", "Folded refusals recorded in summary rows",
             auditor.summarised),
            ("antireplay_audit_refusals_unrecorded",
             "Folded refusals no summary recorded (free space below the floor, trail down)",
             auditor.unrecorded),
            ("antireplay_audit_summary_rows", "Summary rows written", auditor.summaries),
            ("antireplay_audit_spilled_estops", "ESTOP rows spilled to the reserved file",
             receiver.stats.spilled),
            ("antireplay_audit_disk_refusals", "Commands refused below the free-space floor",
             receiver.stats.disk_refusals),
            ("antireplay_audit_rolled_back",
             "Trails found rolled back against the head the state database recorded",
             0 if receiver.audit is None else receiver.audit.rollbacks),
            ("antireplay_audit_head_failures",
             "Audit head checkpoints that could not be written (a failing head key token)",
             0 if receiver.audit is None else receiver.audit.head_failures),
            ("antireplay_audit_rotations_postponed",
             "Due rotations that waited for another writer or reader of the trail",
             0 if receiver.audit is None else receiver.audit.rotations_postponed),
        ):  # fmt: skip
            counter = CounterMetricFamily(name, doc)
            counter.add_metric([], value)
            yield counter
        gauges: list[tuple[str, str, float]] = [
            ("antireplay_audit_refusals_pending", "Folded refusals not summarised yet",
             auditor.pending),
            ("antireplay_audit_head_behind", "1 while the audit head checkpoint cannot be "
             "written (rows reach the trail, its head lags them), else 0",
             0 if receiver.audit is None or receiver.audit.head_behind is None else 1),
        ]  # fmt: skip
        if receiver.space is not None:
            gauges += [
                ("antireplay_audit_free_bytes", "Free bytes under the audit trail",
                 receiver.space.free()),
                ("antireplay_audit_disk_pressure", "0 ok, 1 below min_free_bytes (refusals "
                 "only counted), 2 below refuse_free_bytes (commands refused)",
                 receiver.space.pressure()),
            ]  # fmt: skip
        usage = None if receiver.audit is None else _usage(receiver.audit)
        if usage is not None:
            oldest = math.nan if usage.oldest is None else max(0.0, time.time() - usage.oldest)
            gauges += [
                ("antireplay_audit_trail_bytes", "Bytes the audit trail holds on disk",
                 usage.bytes),
                ("antireplay_audit_trail_segments", "Segments of the audit trail",
                 usage.segments),
                ("antireplay_audit_oldest_row_age_seconds", "Age of the oldest row kept",
                 oldest),
            ]  # fmt: skip
        for name, doc, reading in gauges:
            gauge = GaugeMetricFamily(name, doc)
            gauge.add_metric([], float(reading))
            yield gauge


def _usage(audit: AuditLog) -> TrailUsage | None:
    """The trail's usage, ``None`` when it cannot be read now (closed, deleted)."""
    try:
        return audit.usage()
    except (sqlite3.Error, OSError):
        return None
