"""Metrics for every long-running command: one collector, served to Prometheus on loopback.

Theory of operation
-------------------
:func:`serve_metrics` serves what a ``collect()`` returns at each scrape (a command's
``--metrics-port``, loopback unless the operator names another host);
:func:`router_metrics` turns the MAVLink router's counters into metric families (frames
forwarded and dropped per direction and code, accepted per stream, refusals unaudited or
folded by the rate limit, transport errors per endpoint and kind) and
:func:`serve_router_metrics` serves them.  Counters are read at scrape time, never pushed.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING

from antireplay.wiring.mavlink import MavlinkRefusals

if TYPE_CHECKING:
    from prometheus_client.core import Metric

    from antireplay.mavlink import MavlinkRouter


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
    from prometheus_client.core import CounterMetricFamily  # noqa: PLC0415

    stats = router.stats
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
    return [forwarded, dropped, streams, unaudited, folded, summarised, transport]
