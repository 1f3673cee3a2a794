"""Wiring: the one place that turns configuration into the gateway and the MAVLink router.

The adapters own transport and process lifetime only: :mod:`antireplay.http` speaks HTTP
on built objects, :mod:`antireplay.cli` parses options, reports errors and waits for a
signal.  What a configuration turns into is decided here, the same way for both: open the
replay state, load the keys, open the audit trail, then build the adapter on them.

* :func:`build_receiver` builds the gateway's :class:`~antireplay.rcan.receive.Receiver`
  from :class:`~antireplay.config.AppConfig`: the key registry
  (:func:`build_registry`), the JWT verifier when configured, the store (bounded and
  skewed as ``security`` says) checked for data loss at boot (``verify()``: a store
  that is down now is noticed on the first commit instead), with its anchor outside the
  state directory when ``state.anchor`` names one (:func:`build_anchor`;
  :func:`anchor_warnings` says what a snapshot restore re-opens without it), and the
  audit trail.
* :func:`build_mavlink_router` builds the MAVLink router from the ``mavlink-router``
  options on an opened store and audit trail: its endpoints, an inbound guard per
  key (bound to ``system_id``), the outbound guard, each on its own store prefix
  (``mav-in``, ``mav-out``), a durable timestamp source per key the router signs
  with, and the refusal handler (:func:`mavlink_auditor`), which logs why each
  dropped frame was refused and records it with its direction and the source its
  header claims (``mav:inbound:255/190``, unverified) through the one rate-limited
  :class:`~antireplay.audit.RefusalAuditor`; what it folds is a metric.
  :func:`serve_router_metrics` exposes the router's counters (:func:`router_metrics`)
  to Prometheus through :func:`serve_metrics`, which serves any command's.
* :func:`create_app` hands the receiver, the resolved upstream and its time budget to
  :func:`~antireplay.http.app.gateway_app`; :class:`Guard` and :class:`RcanGuard` are the
  guard middleware and dependency on a receiver built from a configuration (without one,
  :func:`embedded_default`: SQLite under ``./.antireplay/`` and a demo key pair).

The MAVLink stack is imported only when a router is built, so the gateway does not load
the MAVLink dialect.

Size: over 500 lines because it is the one place where configuration becomes objects (the
gateway, its anchor and audit trail, the MAVLink router); splitting it would make two.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from cryptography.hazmat.primitives.asymmetric import ed25519
from starlette.applications import Starlette
from starlette.types import ASGIApp

from antireplay.audit import AuditLog, RefusalAuditor, Retention
from antireplay.audit.space import DiskSpace
from antireplay.config import AppConfig, AuditConfig, KeyConfig
from antireplay.core.clock import Clock
from antireplay.core.errors import ConfigError, StateUnavailableError
from antireplay.http.app import gateway_app
from antireplay.http.dependency import GuardDependency
from antireplay.http.metrics import Metrics
from antireplay.http.middleware import GuardMiddleware
from antireplay.http.upstream import resolve_upstream
from antireplay.rcan.auth import (
    JwtVerifier,
    KeyRegistry,
    load_public_key,
    sdk_key_id,
    write_key_pair,
)
from antireplay.rcan.receive import Receiver
from antireplay.state import ReplayStore, StoreSpec, open_store
from antireplay.state.anchor import StateAnchor, check_anchor_path

if TYPE_CHECKING:
    from prometheus_client.core import Metric

    from antireplay.mavlink import MavlinkRouter, Refusal, Role

DEMO_KID = "demo-operator"
#: How much longer than the upstream budget a QoS retry waits for its original's answer.
ANSWER_SLACK_S = 1.0
#: Audit records and log lines per second for refused MAVLink frames (the rest are counted).
MAVLINK_AUDIT_PER_S = 50.0
log = logging.getLogger("antireplay.mavlink")


def build_registry(config: AppConfig) -> KeyRegistry:
    """The sender keys the configuration names, loaded by the one loader
    (:func:`~antireplay.rcan.auth.load_public_key`: PEM or the RCAN SDK's raw key file; a bad
    key file is a ConfigError), for ``config check`` and ``serve`` alike.  With
    ``sdk_compat``, an ML-DSA-65 key also answers to its SDK key id
    (:func:`~antireplay.rcan.auth.sdk_key_id`), the kid the SDK always signs with."""
    keys = KeyRegistry(sdk_compat=config.sdk_compat)
    added = []
    for entry in config.keys:
        if entry.kid in keys.entries:
            raise ConfigError(f"keys.{entry.kid}.kid", entry.kid, "a kid no other key uses")
        try:
            loaded = tuple(load_public_key(Path(p).read_bytes()) for p in entry.public_keys)
            added.append(keys.add(entry.kid, entry.owner, entry.alg, loaded, set(entry.scopes)))
        except FileNotFoundError as exc:
            raise ConfigError.file_not_found(
                f"keys.{entry.kid}.public_keys", exc.filename
            ) from None
        except (OSError, ValueError) as exc:
            raise ConfigError(
                f"keys.{entry.kid}.public_keys", entry.public_keys, str(exc)
            ) from None
    for key in added if config.sdk_compat else ():
        if key.alg == "ml-dsa-65":
            try:
                keys.alias(sdk_key_id(key.public_keys[0]), key)
            except ValueError as exc:
                allowed = f"a key whose SDK key id no other key uses as its kid ({exc})"
                raise ConfigError(f"keys.{key.kid}.kid", key.kid, allowed) from None
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
        anchor=build_anchor(config),
    )
    with contextlib.suppress(StateUnavailableError):  # down now: noticed on the first commit
        store.verify()  # loss detection at boot, not on the first command
    floors = config.audit_space
    space = DiskSpace(
        config.audit.path, min_free_bytes=floors.min_free_bytes,
        refuse_free_bytes=floors.refuse_free_bytes, clock=clock,
    )  # fmt: skip
    return Receiver(
        config.security,
        build_registry(config),
        store,
        open_audit(config.audit, clock, spill=floors.spill),
        clock,
        space=space,
        jwt=verifier,
        jwt_required=config.jwt.required,
        versions=frozenset(config.versions),
        max_bytes=config.max_body_bytes,
    )


def build_anchor(config: AppConfig) -> StateAnchor | None:
    """The SQLite store's anchor outside its directory (``state.anchor``), if configured."""
    anchor = config.state.anchor
    if not anchor.configured:
        return None
    db = Path(StoreSpec.parse(config.store).target)
    if anchor.path is not None:  # never a file it would damage, nor one a snapshot restores
        check_anchor_path(Path(anchor.path), {
            "state database": db, "state witness": db.with_name(f".{db.name}.witness"),
            "audit trail": Path(config.audit.path),
        })  # fmt: skip
    return StateAnchor(
        db,
        path=anchor.path,
        redis_url=anchor.redis,
        every_s=anchor.every_ms / 1000,
    )


def anchor_summary(config: AppConfig) -> str:
    """What guards the store against a restored copy, for the startup line."""
    anchor = config.state.anchor
    if StoreSpec.parse(config.store).backend != "sqlite":
        return ""
    if not anchor.configured:
        return "no state anchor, "
    places = [
        p for p in (anchor.path, anchor.redis and StoreSpec.parse(anchor.redis).redacted()) if p
    ]
    lazy = f" every {anchor.every_ms} ms" if anchor.every_ms else ""
    return f"anchor {' + '.join(places)}{lazy}, "


def anchor_warnings(config: AppConfig) -> list[str]:
    """What a snapshot restore could re-open with this configuration (``config check``,
    ``serve``): a SQLite store without an anchor, or an anchor file beside the state."""
    spec = StoreSpec.parse(config.store)
    if spec.backend != "sqlite":
        return []
    anchor, window = config.state.anchor, config.security.replay_window_s
    if not anchor.configured:
        return [
            f"store {config.store} has no state anchor (state.anchor): restoring a snapshot "
            f"or backup of its directory within replay_window_s ({window:g} s) of a command "
            "re-opens that command's replay (deleting or restoring the database alone is "
            "detected)"
        ]
    if anchor.path is not None and _same_volume(Path(anchor.path), Path(spec.target)):
        return [
            f"state.anchor.path {anchor.path} is on the same filesystem as {spec.target}: "
            "a snapshot of that volume restores both, which the anchor cannot notice"
        ]
    return []


def _same_volume(one: Path, other: Path) -> bool:
    """Both paths' nearest existing directories are on one filesystem."""

    def device(path: Path) -> int:
        for parent in (path.absolute(), *path.absolute().parents):
            if parent.exists():
                return parent.stat().st_dev
        return -1

    return device(one) == device(other)


def open_audit(
    config: AuditConfig, clock: Clock | None = None, *, spill: str | None = None
) -> AuditLog:
    """The audit trail at ``audit.path``, rotated and retained as ``audit:`` says, with its
    ESTOP spill file (``audit_space.spill``, beside the trail by default)."""
    retention = Retention(
        segment_bytes=config.segment_bytes,
        segment_age_s=config.segment_age_s,
        max_bytes=config.max_bytes,
        max_age_s=config.max_age_s,
    )
    return AuditLog(config.path, clock=clock, retention=retention, spill_path=spill)


def embedded_default(state_dir: Path = Path(".antireplay")) -> AppConfig:
    """SQLite state and audit under ``state_dir`` and a demo Ed25519 key pair (made once)."""
    state_dir.mkdir(parents=True, exist_ok=True)
    private, public = state_dir / f"{DEMO_KID}.key.pem", state_dir / f"{DEMO_KID}.pub.pem"
    if not private.exists():
        write_key_pair(ed25519.Ed25519PrivateKey.generate(), private, public)
    return AppConfig(
        store=f"sqlite:{state_dir / 'state.db'}",
        audit=AuditConfig(path=str(state_dir / "audit.db")),
        keys=[
            KeyConfig(
                kid=DEMO_KID,
                owner="operator",
                alg="ed25519",
                public_keys=[str(public)],
                scopes=["control", "safety"],
            )
        ],
    )


def create_app(config: AppConfig, *, clock: Clock | None = None) -> Starlette:
    """The gateway application for ``config`` (:func:`~antireplay.http.app.gateway_app`)."""
    receiver = build_receiver(config, clock)
    # A retry waits for its original while that is still within its upstream budget.
    receiver.answer_wait_s = config.upstream_timeout_s + ANSWER_SLACK_S
    upstream = resolve_upstream(config.upstream, config.upstream_timeout_s)
    return gateway_app(receiver, upstream, config.upstream_timeout_s)


def _guard_receiver(
    config: AppConfig | None, clock: Clock | None, receiver: Receiver | None
) -> tuple[Receiver, bool]:
    """``receiver``, or one built from ``config`` (the embedded default without one) that
    the guard then owns (its ``close`` closes the audit trail)."""
    if receiver is not None:
        return receiver, False
    return build_receiver(config if config is not None else embedded_default(), clock), True


class Guard(GuardMiddleware):
    """:class:`~antireplay.http.middleware.GuardMiddleware` on ``receiver``, or on one built
    from ``config`` (the embedded default without one; ``clock`` drives it)."""

    def __init__(
        self,
        app: ASGIApp,
        config: AppConfig | None = None,
        *,
        paths: tuple[str, ...] = ("/v1/messages",),
        clock: Clock | None = None,
        receiver: Receiver | None = None,
        metrics: Metrics | None = None,
        accepted: ASGIApp | None = None,
    ) -> None:
        built, owned = _guard_receiver(config, clock, receiver)
        super().__init__(
            app, built, paths=paths, metrics=metrics, accepted=accepted, owns_receiver=owned
        )


class RcanGuard(GuardDependency):
    """:class:`~antireplay.http.dependency.GuardDependency` on ``receiver``, or on one built
    from ``config`` (the embedded default without one; ``clock`` drives it)."""

    def __init__(
        self,
        config: AppConfig | None = None,
        *,
        clock: Clock | None = None,
        receiver: Receiver | None = None,
    ) -> None:
        built, owned = _guard_receiver(config, clock, receiver)
        super().__init__(built, owns_receiver=owned)


def mavlink_auditor(audit: AuditLog, clock: Clock | None = None) -> MavlinkRefusals:
    """The router's ``on_reject``: an audit row and a log line per dropped frame, through
    the rate-limited :class:`~antireplay.audit.RefusalAuditor`."""
    return MavlinkRefusals(RefusalAuditor(audit, clock, per_s=MAVLINK_AUDIT_PER_S, log=log))


@dataclass(frozen=True)
class MavlinkRefusals:
    """A dropped frame on the record: its direction and the source its header claims
    (``mav:inbound:255/190``, unverified).  The router cannot tell which refusals followed
    a verified signature, so every frame spends the unauthenticated budget."""

    auditor: RefusalAuditor

    def close(self) -> None:
        """Write the folded refusals' summary rows (before the trail closes)."""
        self.auditor.close()

    def __call__(self, refusal: Refusal) -> None:
        from antireplay.mavlink import claimed_source  # noqa: PLC0415 - module docstring

        source = claimed_source(refusal.raw)
        claimed = "" if source is None else f":{source[0]}/{source[1]}"
        self.auditor.record(
            code=refusal.code, sender=f"mav:{refusal.direction}{claimed}",
            sender_verified=False, line=str(refusal),
        )  # fmt: skip


@dataclass(frozen=True)
class Allowed:
    """Message ids one direction takes unsigned, and those of them it takes as MAVLink v1."""

    unsigned: frozenset[int] = frozenset()
    v1: frozenset[int] = frozenset()


@dataclass(frozen=True)
class RouterOptions:
    """The ``mavlink-router`` knobs that shape its guards (see :class:`MavlinkGuard`)."""

    system_id: int | None = None
    to_vehicle: Allowed = Allowed()
    from_vehicle: Allowed = Allowed()
    reorder_window: int = 0
    write_through: bool = False
    max_forward_s: float = 60.0
    new_stream_max_age_s: float = 60.0
    sign_link_id: int = 251


def build_mavlink_router(
    endpoints: Sequence[tuple[Role, str, bytes | None]],
    store: ReplayStore,
    audit: AuditLog,
    options: RouterOptions = RouterOptions(),
) -> MavlinkRouter:
    """The router on ``store``: ``endpoints`` are ``(role, connection string, key)``.

    Guards: ``mav-out`` judges the vehicle's frames; ``mav-in`` judges frames to the
    vehicle under the vehicle key, ``mav-in-<key fingerprint>`` those of a ground link
    with a key of its own; the router's signatures take their timestamps from
    ``mav-sign-<fingerprint>-<sign link id>`` (durable; two routers on one store sign
    as different streams when their link ids differ).  Opens every endpoint now: ValueError
    for a bad connection string, OSError naming the one that cannot be opened (those
    already opened are closed again).
    """
    from antireplay.mavlink import (  # noqa: PLC0415 - module docstring
        Link,
        MavlinkGuard,
        MavlinkRouter,
        Role,
        TimestampSource,
        open_transport,
        parse_endpoint,
    )

    specs = [(role, parse_endpoint(text), key) for role, text, key in endpoints]
    vehicle_key = next((key for role, _, key in specs if role is Role.VEHICLE and key), None)
    if vehicle_key is None:
        raise ValueError("a MAVLink router needs a vehicle endpoint with a key")

    def guard(prefix: str, vehicle: int | None, allowed: Allowed, key: bytes) -> MavlinkGuard:
        return MavlinkGuard(
            key, store=store, system_id=vehicle, allow_unsigned=allowed.unsigned,
            allow_v1=allowed.v1, reorder_window=options.reorder_window,
            write_through=options.write_through, store_prefix=prefix,
            max_forward_s=options.max_forward_s,
            new_stream_max_age_s=options.new_stream_max_age_s,
        )  # fmt: skip

    keys = {vehicle_key} | {key for role, _, key in specs if key and role is Role.GROUND}
    names = {key: "" if key == vehicle_key else f"-{_fingerprint(key)}" for key in keys}
    inbound = {
        key: guard(f"mav-in{names[key]}", options.system_id, options.to_vehicle, key)
        for key in keys
    }
    outbound = guard("mav-out", None, options.from_vehicle, vehicle_key)
    signers = {
        key: TimestampSource(
            store=store, store_key=f"mav-sign-{_fingerprint(key)}-{options.sign_link_id}"
        )
        for key in keys
    }
    links: list[Link] = []
    try:
        for role, spec, key in specs:
            try:
                links.append(Link(open_transport(spec), role, key))
            except OSError as exc:
                raise OSError(exc.errno, f"{spec.text}: {exc.strerror or exc}") from exc
    except BaseException:
        for link in links:
            link.transport.close()
        raise
    return MavlinkRouter(
        links, inbound, outbound, signers=signers, sign_link_id=options.sign_link_id,
        on_reject=mavlink_auditor(audit),
    )  # fmt: skip


def stop_router(router: MavlinkRouter) -> None:
    """Stop the router, then write its folded refusals' summary rows (before its audit
    trail closes)."""
    router.stop()
    if isinstance(router.on_reject, MavlinkRefusals):
        router.on_reject.close()


def _fingerprint(key: bytes) -> str:
    """A short public name for a key (store prefixes): not the key, not reversible."""
    return hashlib.sha256(b"antireplay mavlink key" + key).hexdigest()[:12]


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
