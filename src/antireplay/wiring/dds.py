"""The DDS commands, wired: a configuration in, readers, writers and relays out.

Theory of operation
-------------------
A :class:`DdsCommand` is what one ``antireplay dds`` command runs on, built from the one
:class:`~antireplay.config.AppConfig` (its ``dds:`` block; a key outside it was refused by
the loader, naming where it belongs).  It opens the leaves the way every command does
(:mod:`.leaves`): the trail ``dds.audit`` names (else ``audit.path`` if the file names one;
neither: no trail) through :func:`~.leaves.open_trail`, so ``audit:`` retention
(``max_bytes``, ``segment_bytes``, ages), the ESTOP spill and the ``audit_space`` floors
hold for it as for ``serve`` (below the first floor the refusal auditor goes quiet); a
SQLite store through :func:`~.leaves.open_state`, anchored as ``state.anchor`` says; a
signer's state file as a built :class:`~antireplay.state.durable.DurableState`.  Then it
builds the adapter on them (:class:`~antireplay.dds.topics.SealedReader`,
:class:`~antireplay.dds.topics.SealedWriter`,
:class:`~antireplay.dds.relay.AnnouncementRelay` with its ping listener), handing down only
built objects and values.  :meth:`DdsCommand.metrics` gives a command's counters to
``--metrics-port`` (:func:`~.metrics.serve_metrics`).  :meth:`DdsCommand.close` closes what
it opened in reverse order: endpoints (their folded refusals' summary rows) before their
stores and the trail.

Cyclone DDS is imported with this module, which only the ``dds`` commands import.
"""

from __future__ import annotations

import contextlib
import os
from collections import Counter
from collections.abc import Callable
from typing import TYPE_CHECKING

from antireplay.audit import AuditLog
from antireplay.config import AppConfig
from antireplay.config.dds import DdsConfig, RelayConfig, parse_udp
from antireplay.core.clock import Clock
from antireplay.core.errors import ConfigError
from antireplay.dds.domain import join_domain
from antireplay.dds.ping import PingListener
from antireplay.dds.relay import AnnouncementRelay
from antireplay.dds.topics import SealedReader, SealedWriter
from antireplay.epochs import signer_state
from antireplay.state import ReplayStore, StoreSpec, open_store
from antireplay.wiring.leaves import open_state, open_trail

if TYPE_CHECKING:
    from prometheus_client.core import Metric


class DdsCommand:
    """One ``dds`` command's participant, fleet key and trail, and the endpoints built on
    them; everything it opened is closed by :meth:`close`."""

    def __init__(self, config: AppConfig, *, clock: Clock | None = None) -> None:
        if config.dds is None:
            raise ConfigError("dds", None, "a dds: block (a mapping with at least psk_file)")
        self.config, self.block, self.clock = config, config.dds, clock
        self._opened = contextlib.ExitStack()
        self.psk = self.block.psk()
        self.rotation = self.block.rotation()  # the fleet key's successor, read at start
        self.audit: AuditLog | None = None
        #: True while free space under the trail is below ``audit_space.min_free_bytes``.
        self.quiet: Callable[[], bool] | None = None
        path = self.block.audit or (config.audit.path if config.audit.path_set() else None)
        if path is not None:
            audit, space = open_trail(config, path, clock)
            self._opened.callback(audit.close)
            self.audit, self.quiet = audit, space.low
        self.participant = join_domain(self.block.domain_id, loopback=self.block.loopback_only)
        # Left explicitly on close: peers hear the endpoints go at once (a writer waiting for
        # this reader's acknowledgement stops waiting) instead of after the lease expires.
        self._opened.callback(self.participant.__del__)

    @property
    def domain_id(self) -> int:
        return self.block.domain_id

    def close(self) -> None:
        """Close every endpoint, store and trail opened, the last opened first."""
        self._opened.close()

    def __enter__(self) -> DdsCommand:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def metrics(self, counts: dict[str, Counter[str]]) -> list[Metric]:
        """The command's counters now, for ``--metrics-port``: verdicts per endpoint and
        outcome (``counts``: endpoint name -> its counter, read at scrape time) and, with a
        trail, the bytes and segments it holds on disk."""
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily  # noqa: PLC0415

        verdicts = CounterMetricFamily(
            "antireplay_dds_verdicts",
            "Samples, pings, challenges and answers judged, per endpoint and outcome",
            labels=["endpoint", "outcome"],
        )
        for endpoint, counter in counts.items():
            for outcome, n in list(counter.items()):
                verdicts.add_metric([endpoint, outcome], n)
        found: list[Metric] = [verdicts]
        if self.audit is not None:
            usage = self.audit.usage()
            for name, doc, value in (
                ("antireplay_audit_trail_bytes", "Bytes the audit trail holds on disk",
                 usage.bytes),
                ("antireplay_audit_trail_segments", "Segments of the audit trail",
                 usage.segments),
            ):  # fmt: skip
                found.append(GaugeMetricFamily(name, doc, value=value))
        return found

    def store(self, text: str) -> ReplayStore:
        """The replay store ``text`` names: SQLite through the leaves (anchored when
        ``state.anchor`` is set), memory or Redis as the spec says."""
        spec = StoreSpec.parse(text)
        if spec.backend == "sqlite":
            audit_path = self.audit.path if self.audit is not None else self.config.audit.path
            store = open_state(self.config, spec, audit_path=str(audit_path), clock=self.clock)
        else:
            store = open_store(spec, clock=self.clock)
        self._opened.callback(store.close)
        return store

    def reader(self, topic: str | None = None) -> SealedReader:
        """A sealed reader on ``topic`` (default ``dds.reader.topic``) on ``dds.reader.store``."""
        block = self.block
        reader = SealedReader(
            self.participant,
            topic or block.reader.topic,
            self.psk,
            store=self.store(block.reader.store),
            clock=self.clock,
            max_age_s=block.max_age_s,
            max_forward_s=block.max_forward_s,
            audit=self.audit,
            quiet=self.quiet,
            rotation=self.rotation,
        )
        self._opened.callback(reader.close)
        return reader

    def writer(self, topic: str | None = None) -> SealedWriter:
        """A sealed writer on ``topic`` (default ``dds.writer.topic``), resuming from
        ``dds.writer.state_file`` when set."""
        block = self.block
        path = block.writer.state_file
        writer = SealedWriter(
            self.participant,
            topic or block.writer.topic,
            self.psk,
            state=None if path is None else signer_state(path),
            clock=self.clock,
            max_forward_s=block.max_forward_s,
            rotation=self.rotation,
        )
        self._opened.callback(writer.close)
        return writer

    def rogue(self, topic: str) -> SealedWriter:
        """The attacker's writer of ``dds replay``: a key of its own, not the fleet's."""
        return SealedWriter(self.participant, topic, os.urandom(32), clock=self.clock)

    def relay(self) -> AnnouncementRelay:
        """The announcement relay ``dds.relay`` describes, with its ping listener."""
        block = self.block
        relay = _relay_block(block)
        ping = None
        if relay.ping_listen is not None:
            ping = PingListener(
                self.psk, bind=parse_udp(relay.ping_listen), clock=self.clock,
                max_age_s=block.max_age_s, max_forward_s=block.max_forward_s,
                audit=self.audit, quiet=self.quiet,
            )  # fmt: skip
            self._opened.callback(ping.close)
        service = AnnouncementRelay(
            self.participant,
            self.psk,
            service_name=relay.service_name,
            signer_state=signer_state(relay.signer_state),
            verifier_store=self.store(relay.verifier_store),
            clock=self.clock,
            max_age_s=block.max_age_s,
            max_forward_s=block.max_forward_s,
            audit=self.audit,
            ping=ping,
            quiet=self.quiet,
            rotation=self.rotation,
        )
        self._opened.callback(service.close)
        return service


def _relay_block(block: DdsConfig) -> RelayConfig:
    if block.relay is None:
        raise ConfigError(
            "dds.relay", None, "a relay block (service_name, signer_state, verifier_store)"
        )
    return block.relay


__all__ = ["DdsCommand"]
