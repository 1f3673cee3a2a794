"""The post-quantum ends, wired: a ``mavlink_pq:`` block in, a running link's parts out.

Theory of operation
-------------------
:func:`open_pq_end` is all ``mavlink-pq ground|vehicle`` does between reading its
configuration and waiting for a signal, leaves first: the end's keys (PEM files from
``antireplay keygen``, loaded and type-checked here: :func:`ground_end`,
:func:`vehicle_end`), its two transports, and its audit trail with its retention, spill
and free-space floors through :func:`~antireplay.wiring.leaves.open_trail`, the function
``serve`` opens its own through.  Then the :class:`~antireplay.mavlink.pq.link.PqLink` on
them: refusals go to the rate-limited refusal auditor (quiet below the first floor), and
a change of the session (established, rekeyed, lost, resumed) is logged at INFO and
always audited (:func:`session_recorder`: it is authentic, and rare); a verified refusal
of the ground end's handshake is logged as a warning, once per reason.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from cryptography.exceptions import UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import mldsa, mlkem, x25519

from antireplay.audit import AuditLog, AuditRow
from antireplay.audit.space import DiskSpace
from antireplay.config import AppConfig, PqGroundConfig, PqVehicleConfig
from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import ConfigError
from antireplay.wiring.leaves import open_trail, trail_path
from antireplay.wiring.refusals import MavlinkRefusals, mavlink_auditor

if TYPE_CHECKING:
    from antireplay.mavlink.endpoints import Transport
    from antireplay.mavlink.pq import GroundEnd, VehicleEnd
    from antireplay.mavlink.pq.link import PqLink, SessionEvent

log = logging.getLogger("antireplay.mavlink.pq")


def pq_audit_path(config: AppConfig, end: str) -> str:
    """An end's trail: ``audit.path`` when the file (or ``--audit``) names it, else its own."""
    return trail_path(config, f".antireplay/mavlink-pq-{end}-audit.db")


def load_pem(path: str, kind: Any, key: str) -> Any:
    """The PEM key of type ``kind`` in ``path`` (private or public, as ``kind`` is)."""
    private = "Private" in kind.__name__
    what = "an unencrypted PEM private key" if private else "a PEM public key"
    try:
        data = Path(path).read_bytes()
        loaded = (
            serialization.load_pem_private_key(data, None)
            if private
            else serialization.load_pem_public_key(data)
        )
    except (OSError, ValueError, TypeError, UnsupportedAlgorithm) as exc:
        raise ConfigError(key, path, what, message=f"{key} {path}: not {what} ({exc})") from None
    if not isinstance(loaded, kind):
        said = f"{key} {path}: a {type(loaded).__name__}, not a {kind.__name__}"
        raise ConfigError(key, path, f"a {kind.__name__}", message=said)
    return loaded


def _required(value: str | None, key: str, flag: str) -> str:
    if value is None:
        raise ConfigError(key, None, "a value", message=f"give {flag} (or {key})")
    return value


def ground_end(section: PqGroundConfig) -> GroundEnd:
    """The end next to the ground station, its keys loaded (``mavlink_pq.ground``)."""
    from antireplay.mavlink.pq import GroundEnd  # noqa: PLC0415 - the dialect loads on use
    from antireplay.pq.session import Initiator  # noqa: PLC0415

    at = "mavlink_pq.ground"
    signing = _required(section.signing_key, f"{at}.signing_key", "--signing-key")
    vehicle = _required(section.vehicle_key, f"{at}.vehicle_key", "--vehicle-key")
    key = load_pem(signing, mldsa.MLDSA87PrivateKey, f"{at}.signing_key")
    kem = load_pem(vehicle, mlkem.MLKEM1024PublicKey, f"{at}.vehicle_key")
    hybrid = None
    if section.vehicle_x25519 is not None:
        hybrid = load_pem(section.vehicle_x25519, x25519.X25519PublicKey, f"{at}.vehicle_x25519")
    try:
        initiator = Initiator(section.identity, key)
    except ValueError as exc:
        raise ConfigError(f"{at}.identity", section.identity, str(exc)) from None
    return GroundEnd(
        initiator, kem, system_id=section.system_id, hybrid=hybrid,
        queue_ttl_s=section.queue_ttl_s, air_bps=section.air_bps,
    )  # fmt: skip


def vehicle_end(section: PqVehicleConfig) -> VehicleEnd:
    """The end next to the autopilot, its keys loaded (``mavlink_pq.vehicle``)."""
    from antireplay.mavlink.pq import VehicleEnd  # noqa: PLC0415 - the dialect loads on use
    from antireplay.pq.session import Responder  # noqa: PLC0415

    at = "mavlink_pq.vehicle"
    kem_key = _required(section.kem_key, f"{at}.kem_key", "--kem-key")
    kem = load_pem(kem_key, mlkem.MLKEM1024PrivateKey, f"{at}.kem_key")
    if not section.peers:
        raise ConfigError(f"{at}.peers", {}, "a value", message=f"give --peer (or {at}.peers)")
    registry = {
        name: load_pem(path, mldsa.MLDSA87PublicKey, f"{at}.peers.{name}")
        for name, path in section.peers.items()
    }
    hybrid = None
    if section.x25519_key is not None:
        hybrid = load_pem(section.x25519_key, x25519.X25519PrivateKey, f"{at}.x25519_key")
    responder = Responder(kem, registry, max_sessions=section.max_sessions, x25519_key=hybrid)
    return VehicleEnd(
        responder, system_id=section.system_id, max_age_s=section.max_age_s,
        air_bps=section.air_bps,
    )  # fmt: skip


def session_recorder(audit: AuditLog, clock: Clock | None = None) -> Callable[[SessionEvent], None]:
    """Log a session change at INFO and audit it (always: it is authentic, and rare)."""
    clock = resolve(clock)

    def record(event: SessionEvent) -> None:
        log.info("%s", event)
        audit.append(
            AuditRow(clock.wall(), "session", event.kind.upper(), sender=f"pq:{event.peer}",
                     sender_verified=True, msg_id=event.session_id.hex())
        )  # fmt: skip

    return record


@dataclass
class PqParts:
    """What ``mavlink-pq ground|vehicle`` runs and closes: the link on its trail."""

    link: PqLink
    local: str
    air: str
    audit: AuditLog
    space: DiskSpace
    refusals: MavlinkRefusals

    def close(self) -> None:
        """Stop the link, record the folded refusals, then close the trail."""
        self.link.stop()
        self.refusals.close()  # the folded refusals' summary rows, before the trail closes
        self.audit.close()


def open_pq_end(
    config: AppConfig, which: Literal["ground", "vehicle"], audit_path: str | None = None
) -> PqParts:
    """The end the ``mavlink_pq.<which>`` block describes on its transports and audit trail
    (at ``audit_path``; default :func:`pq_audit_path`), opened as ``serve`` opens its own.

    Raises ConfigError (a key, a key file), ValueError (an endpoint string), OSError (an
    endpoint that cannot be opened), StateFileError (the trail)."""
    from antireplay.mavlink.endpoints import open_transport, parse_endpoint  # noqa: PLC0415
    from antireplay.mavlink.pq.link import PqLink  # noqa: PLC0415

    section: PqGroundConfig | PqVehicleConfig
    if which == "ground":
        section = config.mavlink_pq.ground
        end: GroundEnd | VehicleEnd = ground_end(section)
        local = section.local
    else:
        section = config.mavlink_pq.vehicle
        end = vehicle_end(section)
        local = _required(section.fc, "mavlink_pq.vehicle.fc", "--fc")
    air = _required(section.air, f"mavlink_pq.{which}.air", "--air")
    transports: list[Transport] = []
    try:
        for text in (local, air):
            spec = parse_endpoint(text)
            try:
                transports.append(open_transport(spec))
            except OSError as exc:
                raise OSError(exc.errno, f"{text}: {exc.strerror or exc}") from exc
        audit, space = open_trail(config, audit_path or pq_audit_path(config, which))
    except BaseException:
        for transport in transports:
            transport.close()
        raise
    refusals = mavlink_auditor(audit, quiet=space.low)
    link = PqLink(
        end, *transports, on_reject=refusals, on_session=session_recorder(audit),
        on_notice=log.warning, air_bps=section.air_bps,
    )  # fmt: skip
    return PqParts(link, local, air, audit, space, refusals)
