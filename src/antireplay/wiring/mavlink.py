"""The MAVLink router and the post-quantum ends, wired: options in, a router or a link out.

Theory of operation
-------------------
:func:`build_mavlink_router` builds the router on an opened store and audit trail: its
endpoints, an inbound guard per key (bound to ``system_id``), the outbound guard, each on
its own store prefix (``mav-in``, ``mav-out``), a durable timestamp source per key the
router signs with, and the refusal handler (:func:`mavlink_auditor`), which logs why each
dropped frame was refused and records it with its direction and the source its header
claims (``mav:inbound:255/190``, unverified) through the one rate-limited
:class:`~antireplay.audit.RefusalAuditor`; what it folds is a metric.  The MAVLink stack
is imported only when a router is built, so the gateway does not load the MAVLink dialect.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from antireplay.audit import AuditLog, RefusalAuditor
from antireplay.core.clock import Clock
from antireplay.state import ReplayStore

if TYPE_CHECKING:
    from antireplay.mavlink import MavlinkRouter, Refusal, Role

MAVLINK_AUDIT_PER_S = 50.0
log = logging.getLogger("antireplay.mavlink")


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
