"""Metrics for every long-running command: one collector, served to Prometheus on loopback.

Theory of operation
-------------------
:func:`serve_metrics` serves what a ``collect()`` returns at each scrape (a command's
``--metrics-port``, loopback unless the operator names another host);
:func:`router_metrics` turns the MAVLink router's counters into metric families (frames
forwarded and dropped per direction and code, accepted per stream, refusals unaudited or
folded by the rate limit, transport errors per endpoint and kind) and
:func:`serve_router_metrics` serves them; :func:`pq_metrics` does the same for a
post-quantum end's link (sessions, handshakes, chunks, air bytes by kind, repairs).
:func:`trail_metrics` is what the gateway exports about its leaves, for any command: the
trail's bytes and segments, the free space under it and the pressure against its floors,
and readiness (the store could take a commit, the trail an append: the gateway's
``/readyz``) as a gauge.  Counters are read at scrape time, never pushed.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING

from antireplay.audit import AuditLog
from antireplay.audit.space import DiskSpace
from antireplay.http.readiness import audit_problem
from antireplay.state import ReplayStore
from antireplay.wiring.refusals import MavlinkRefusals

if TYPE_CHECKING:
    from prometheus_client.core import Metric

    from antireplay.mavlink import MavlinkRouter
    from antireplay.mavlink.pq.link import LinkCounts


def serve_metrics(
    collect: Callable[[], Iterable[Metric]], port: int, host: str = "127.0.0.1"
) -> None:
    """Serve what ``collect()`` returns at each scrape to Prometheus on ``host:port``
    (loopback by default): a long-running command's ``--metrics-port``."""
    from prometheus_client import REGISTRY, start_http_server  # noqa: PLC0415
    from prometheus_client.registry import Collector  # noqa: PLC0415

    class CommandCollector(Collector):
        def collect(self) -> Iterator[Metric]:
            return iter(collect())

    REGISTRY.register(CommandCollector())
    start_http_server(port, addr=host)


def serve_router_metrics(router: MavlinkRouter, port: int, host: str = "127.0.0.1") -> None:
    """Serve :func:`router_metrics` to Prometheus on ``host:port`` (loopback by default)."""
    serve_metrics(lambda: router_metrics(router), port, host)


def router_metrics(router: MavlinkRouter) -> list[Metric]:
    """The router's counters now: frames forwarded per direction, dropped per direction
    and code, accepted per stream, refusals left unaudited (trail down) or folded by the
    rate limit, transport errors per endpoint and kind."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily  # noqa: PLC0415

    stats = router.stats
    network = GaugeMetricFamily(
        "antireplay_mavlink_network_trusted_endpoints",
        "Trusted (signed-on-behalf) endpoints the operator acknowledged on the network",
    )
    network.add_metric([], sum(link.network for link in router.links))
    forwarded = CounterMetricFamily(
        "antireplay_mavlink_forwarded", "Frames forwarded", labels=["direction"]
    )
    for direction, n in list(stats.forwarded.items()):
        forwarded.add_metric([direction], n)
    dropped = CounterMetricFamily(
        "antireplay_mavlink_dropped", "Frames dropped", labels=["direction", "code"]
    )
    for label, n in list(stats.dropped.items()):
        direction, _, code = label.partition(":")
        dropped.add_metric([direction, code], n)
    streams = CounterMetricFamily(
        "antireplay_mavlink_stream_frames",
        "Authenticated frames accepted per stream",
        labels=["endpoint", "system", "component", "link"],
    )
    for (endpoint, system, component, link_id), n in list(stats.streams.items()):
        streams.add_metric([endpoint, str(system), str(component), str(link_id)], n)
    unaudited = CounterMetricFamily(
        "antireplay_mavlink_refusals_unaudited",
        "Refused frames the audit trail could not record (it was down)",
    )
    unaudited.add_metric([], stats.unaudited)
    transport = CounterMetricFamily(
        "antireplay_mavlink_transport_errors",
        "Transport errors per endpoint and kind (connect, send, stalled, eof, reopen, ...)",
        labels=["endpoint", "kind"],
    )
    for link in router.links:
        for kind, n in list(link.transport.errors.items()):
            transport.add_metric([link.name, kind], n)
    folded = CounterMetricFamily(
        "antireplay_mavlink_refusals_rate_limited",
        "Refused frames left off the audit trail and the log by the rate limit, per class",
        labels=["class"],
    )
    summarised = CounterMetricFamily(
        "antireplay_mavlink_refusals_summarised",
        "Folded refusals on the record as summary rows, or that no summary recorded",
        labels=["state"],
    )
    if isinstance(router.on_reject, MavlinkRefusals):
        auditor = router.on_reject.auditor
        for cls in ("authenticated", "unauthenticated"):
            folded.add_metric([cls], auditor.folded[cls])
        summarised.add_metric(["recorded"], auditor.summarised)
        summarised.add_metric(["unrecorded"], auditor.unrecorded)
    return [forwarded, dropped, streams, unaudited, folded, summarised, transport, network]


def pq_metrics(counts: LinkCounts) -> list[Metric]:
    """A link's counts as Prometheus metrics, labelled with its end (ground, vehicle)."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily  # noqa: PLC0415

    from antireplay.mavlink.pq.link import SESSION_EVENTS  # noqa: PLC0415
    from antireplay.mavlink.pq.repair import AIR_KINDS  # noqa: PLC0415

    end = counts.end
    up = GaugeMetricFamily(
        "antireplay_mavlink_pq_session_up",
        "1 while a session is live (the other end heard within its silence limit)",
        labels=["end"],
    )
    up.add_metric([end], int(counts.up))
    families: list[Metric] = [up]
    for name, text, label, fixed, counter in (
        ("sessions", "Session changes", "event", SESSION_EVENTS, counts.sessions),
        ("handshakes", "Handshakes", "outcome", ("started", "completed", "failed", "refused"),
         counts.handshakes),
        ("handshake_refusals", "PQ_REFUSALs: sent or withheld (vehicle end: one per HS1, "
         "within its airtime budget); verified, forged, stale or elsewhere (ground end)",
         "outcome", ("sent", "withheld", "verified", "forged", "stale", "elsewhere"),
         counts.handshake_refusals),
        ("chunks", "PQ_CHUNK frames", "what", ("sent", "received", "reassembled"),
         counts.chunks),
        ("air_bytes", "Bytes handed to the air, by what they carry", "kind", AIR_KINDS,
         counts.airtime),
        ("repairs", "Repair requests sent, chunks resent, held answers sent again", "what",
         ("nack_sent", "poke_sent", "resent", "answered", "ignored", "withheld"),
         counts.repairs),
        ("retries", "A ground station's command retries, by how they were answered", "how",
         ("poked", "answered", "sending", "queued"), counts.retries),
    ):  # fmt: skip
        family = CounterMetricFamily(f"antireplay_mavlink_pq_{name}", text, labels=["end", label])
        for key in fixed:
            family.add_metric([end, key], counter[key])
        families.append(family)
    for name, text, label, counter in (
        ("refusals", "Frames refused, by side and code", "code", counts.refused),
        ("dropped", "Frames dropped without a refusal (no session, queue, reassembly, plain)",
         "reason", counts.dropped),
    ):  # fmt: skip
        family = CounterMetricFamily(
            f"antireplay_mavlink_pq_{name}", text, labels=["end", "side", label]
        )
        for key, n in sorted(counter.items()):
            side, _, what = key.partition(":")
            family.add_metric([end, side, what], n)
        families.append(family)
    unaudited = CounterMetricFamily(
        "antireplay_mavlink_pq_unaudited",
        "Refusals and session changes the audit trail could not record (it was down)",
        labels=["end"],
    )
    unaudited.add_metric([end], counts.unaudited)
    return [*families, unaudited]


def leaves_ready(audit: AuditLog, space: DiskSpace, store: ReplayStore | None = None) -> str | None:
    """Why a command cannot take traffic now (its store, the disk, its trail), ``None`` if it
    can: the gateway's readiness for any command's leaves.  Blocking I/O; records nothing."""
    if store is not None:
        try:
            store.ready()
        except Exception as exc:  # any backend's failure is the reason
            return f"store: {exc}"
    return space.reason() or audit_problem(audit)


def trail_metrics(
    command: str,
    audit: AuditLog,
    space: DiskSpace,
    store: ReplayStore | None = None,
    fenced: Callable[[], str | None] | None = None,
) -> list[Metric]:
    """A command's leaves as the gateway exports its own: readiness, the trail on disk,
    the free space under it and the pressure against its floors.  ``fenced`` says why the
    command refuses everything stamped now (a restart fence), ``None`` if it does not:
    readiness is 0 meanwhile."""
    from prometheus_client.core import GaugeMetricFamily  # noqa: PLC0415

    ready = GaugeMetricFamily(
        "antireplay_ready", "1 while the store takes a commit and the audit trail an append "
        "(and no restart fence refuses what is stamped now)",
        labels=["command"],
    )  # fmt: skip
    unready = (fenced() if fenced is not None else None) or leaves_ready(audit, space, store)
    ready.add_metric([command], int(unready is None))
    families: list[Metric] = [ready]
    values: list[tuple[str, str, float]] = [
        ("antireplay_audit_free_bytes", "Free bytes under the audit trail", space.free()),
        ("antireplay_audit_disk_pressure", "0 ok, 1 below min_free_bytes (refusals only "
         "counted), 2 below refuse_free_bytes", space.pressure()),
    ]  # fmt: skip
    try:
        usage = audit.usage()
    except (sqlite3.Error, OSError):  # closed or deleted meanwhile: said by readiness
        usage = None
    if usage is not None:
        values += [
            ("antireplay_audit_trail_bytes", "Bytes the audit trail holds on disk", usage.bytes),
            ("antireplay_audit_trail_segments", "Segments of the audit trail", usage.segments),
        ]
    for name, doc, value in values:
        gauge = GaugeMetricFamily(name, doc, labels=["command"])
        gauge.add_metric([command], value)
        families.append(gauge)
    return families
