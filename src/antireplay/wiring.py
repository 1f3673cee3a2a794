"""Wiring: the one place that turns configuration into the gateway's Receiver and the MAVLink proxy.

Theory of operation
-------------------
The adapters own transport and process lifetime only: :mod:`antireplay.gateway`
speaks HTTP, :mod:`antireplay.cli` parses options, reports errors and waits for a
signal.  What a configuration turns into is decided here, the same way for both:
open the replay state, load the keys, open the audit trail, then build the policy
object on them.

* :func:`build_receiver` builds the gateway's :class:`~antireplay.pipeline.Receiver`
  from :class:`~antireplay.config.AppConfig`: the key registry
  (:func:`build_registry`), the JWT verifier when configured, the store (bounded and
  skewed as ``security`` says) checked for data loss at boot (``verify()``: a store
  that is down now is noticed on the first commit instead), and the audit trail.
* :func:`build_mavlink_proxy` builds the MAVLink proxy from the ``mavlink-proxy``
  options on an opened store and audit trail: an inbound guard (bound to
  ``system_id``) and an outbound guard on their own store prefixes (``mav-in``,
  ``mav-out``), and the rejection auditor (:func:`mavlink_auditor`), which records
  each dropped frame with its direction and the source its header claims
  (``mav:inbound:255/190``; unverified, so ``sender_verified`` is false),
  rate-limited so that a flood of garbage cannot grow the trail without bound.
  :func:`serve_proxy_metrics` exposes the proxy's counters to Prometheus.

The MAVLink stack is imported only when a proxy is built, so the gateway does not
load the MAVLink dialect.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from antireplay.audit import AuditLog
from antireplay.auth import JwtVerifier, KeyRegistry, load_public_key
from antireplay.clock import Clock, resolve
from antireplay.config import AppConfig
from antireplay.errors import ConfigError, ReplayAttackError, StateUnavailableError
from antireplay.pipeline import Receiver, TokenBucket
from antireplay.stores import ReplayStore, open_store

if TYPE_CHECKING:
    from prometheus_client.core import Metric

    from antireplay.mavlink import MavlinkProxy

#: Audit records per second for rejected MAVLink frames (the rest are only counted).
MAVLINK_AUDIT_PER_S = 50.0
Rejection = Callable[[str, ReplayAttackError, bytes], None]


def build_registry(config: AppConfig) -> KeyRegistry:
    """The sender keys the configuration names, loaded (a bad key file is a ConfigError)."""
    keys = KeyRegistry(sdk_compat=config.sdk_compat)
    for entry in config.keys:
        try:
            loaded = tuple(load_public_key(Path(p).read_bytes()) for p in entry.public_keys)
            keys.add(entry.kid, entry.owner, entry.alg, loaded, set(entry.scopes))
        except (OSError, ValueError) as exc:
            raise ConfigError(
                f"keys.{entry.kid}.public_keys", entry.public_keys, str(exc)
            ) from None
    return keys


def build_receiver(config: AppConfig, clock: Clock | None = None) -> Receiver:
    """Wire a Receiver from configuration: keys, store, audit, JWT."""
    verifier = None
    if config.jwt.keys or config.jwt.hs256_secret_env:
        secret = os.environ.get(config.jwt.hs256_secret_env or "", "") or None
        verifier = JwtVerifier(
            {kid: load_public_key(Path(p).read_bytes()) for kid, p in config.jwt.keys.items()},
            audience=config.jwt.audience,
            issuer=config.jwt.issuer,
            hs256_secret=secret.encode() if secret else None,
            leeway_s=config.jwt.leeway_s,
            clock=clock,
        )
    store = open_store(
        config.store,
        clock=clock,
        max_entries=config.security.msg_id_cache_size,
        skew_s=config.security.skew_s,
    )
    with contextlib.suppress(StateUnavailableError):  # down now: noticed on the first commit
        store.verify()  # loss detection at boot, not on the first command
    return Receiver(
        config.security,
        build_registry(config),
        store,
        AuditLog(config.audit),
        clock,
        jwt=verifier,
        jwt_required=config.jwt.required,
        versions=frozenset(config.versions),
        max_bytes=config.max_body_bytes,
    )


def mavlink_auditor(audit: AuditLog, clock: Clock | None = None) -> Rejection:
    """The proxy's ``on_reject``: one audit record per dropped frame, rate-limited."""
    from antireplay.mavlink import claimed_source  # noqa: PLC0415 - module docstring

    clock = resolve(clock)
    bucket = TokenBucket(MAVLINK_AUDIT_PER_S, clock)

    def audit_reject(direction: str, exc: ReplayAttackError, raw: bytes) -> None:
        if not bucket.take():
            return
        source = claimed_source(raw)
        claimed = "" if source is None else f":{source[0]}/{source[1]}"
        audit.append(
            at=clock.wall(), outcome="rejected", code=str(exc.code), warning=None,
            msg_type=None, sender=f"mav:{direction}{claimed}", sender_verified=False,
            msg_id=None,
        )  # fmt: skip

    return audit_reject


def build_mavlink_proxy(
    listen: tuple[str, int],
    forward: tuple[str, int],
    key: bytes,
    store: ReplayStore,
    audit: AuditLog,
    *,
    system_id: int | None = None,
    allow_unsigned: frozenset[int] = frozenset(),
    reorder_window: int = 0,
    write_through: bool = False,
) -> MavlinkProxy:
    """The two guards on ``store`` and the proxy between them (binds ``listen``: OSError)."""
    from antireplay.mavlink import MavlinkGuard, MavlinkProxy  # noqa: PLC0415 - module docstring

    def guard(prefix: str, vehicle: int | None) -> MavlinkGuard:
        return MavlinkGuard(
            key, store=store, system_id=vehicle, allow_unsigned=allow_unsigned,
            reorder_window=reorder_window, write_through=write_through, store_prefix=prefix,
        )  # fmt: skip

    inbound, outbound = guard("mav-in", system_id), guard("mav-out", None)
    return MavlinkProxy(listen, forward, inbound, outbound, mavlink_auditor(audit))


def serve_proxy_metrics(proxy: MavlinkProxy, port: int) -> None:
    """Serve the proxy's forwarded and dropped counters to Prometheus on loopback ``port``."""
    from prometheus_client import REGISTRY, start_http_server  # noqa: PLC0415
    from prometheus_client.core import CounterMetricFamily  # noqa: PLC0415
    from prometheus_client.registry import Collector  # noqa: PLC0415

    class ProxyCollector(Collector):
        def collect(self) -> Iterator[Metric]:
            forwarded = CounterMetricFamily(
                "antireplay_mavlink_forwarded", "Frames forwarded", labels=["direction"]
            )
            for direction, n in proxy.stats.forwarded.items():
                forwarded.add_metric([direction], n)
            dropped = CounterMetricFamily(
                "antireplay_mavlink_dropped", "Frames dropped", labels=["direction", "code"]
            )
            for label, n in proxy.stats.dropped.items():
                direction, _, code = label.partition(":")
                dropped.add_metric([direction, code], n)
            yield forwarded
            yield dropped

    REGISTRY.register(ProxyCollector())
    start_http_server(port, addr="127.0.0.1")
