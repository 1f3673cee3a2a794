"""``antireplay mavlink-pq ground|vehicle``: the two post-quantum ends as commands.

Registered by :mod:`antireplay.cli`; it lives outside :mod:`antireplay.mavlink` so that
the pymavlink dialect is imported only when a command runs.
Keys are PEM files from ``antireplay keygen`` (``--alg ml-dsa-87`` for the operator,
``ml-kem-1024`` and, for the hybrid option, ``x25519`` for the vehicle).  Each command
runs one :class:`~antireplay.mavlink.pq.link.PqLink` until SIGINT or SIGTERM and prints
the counts when it stops.  Refusals go to the rate-limited refusal auditor (an audit
record and a log line each, the rest counted); a change of the session (established,
rekeyed, lost, resumed) is logged at INFO and always audited (``--audit``).  With
``--metrics-port`` the link's counts (:func:`pq_metrics`) are served to Prometheus, air
bytes by kind among them; ``--air-bps`` paces the air side to the radio's serial rate.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click
from cryptography.exceptions import UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import mldsa, mlkem, x25519

from antireplay.audit import AuditLog
from antireplay.cli._common import (
    _MOVE_ASIDE,
    _check_audit_file,
    _fail,
    stop_on_signal,
    warn_if_shared,
    why,
)
from antireplay.core.clock import SystemClock
from antireplay.core.errors import StateFileError

if TYPE_CHECKING:
    from prometheus_client.core import Metric

    from antireplay.mavlink.pq import GroundEnd, VehicleEnd
    from antireplay.mavlink.pq.link import LinkCounts, SessionEvent

log = logging.getLogger("antireplay.mavlink.pq")
PEM = click.Path(path_type=Path, dir_okay=False, exists=True)
F = TypeVar("F", bound=Callable[..., Any])


def _operations(end: str) -> Callable[[F], F]:
    """The options every end shares: its audit trail, its metrics port, its air budget."""

    def apply(command: F) -> F:
        for option in (
            click.option(
                "--audit", "audit_path", default=f".antireplay/mavlink-pq-{end}-audit.db",
                show_default=True, help="The audit trail: refusals and session changes.",
            ),
            click.option(
                "--metrics-port", type=click.IntRange(0, 65535), default=None,
                help="Serve Prometheus metrics here.",
            ),
            click.option(
                "--metrics-host", default="127.0.0.1", show_default=True,
                help="The address the metrics port binds (0.0.0.0 for a Prometheus on "
                "another host).",
            ),
            click.option(
                "--air-bps", type=click.IntRange(1_200, 10_000_000), default=None,
                help="The radio's serial rate in baud (57600 for a SiK radio): pace what "
                "goes on air to it, telemetry ahead of long transfers.  Default: unpaced.",
            ),
        ):  # fmt: skip
            command = option(command)
        return command

    return apply


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
        ("handshakes", "Handshakes", "outcome", ("started", "completed", "failed"),
         counts.handshakes),
        ("chunks", "PQ_CHUNK frames", "what", ("sent", "received", "reassembled"),
         counts.chunks),
        ("air_bytes", "Bytes handed to the air, by what they carry", "kind", AIR_KINDS,
         counts.airtime),
        ("repairs", "Repair requests sent, chunks resent, held answers sent again", "what",
         ("nack_sent", "poke_sent", "resent", "answered", "ignored"), counts.repairs),
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


def _key(path: Path, kind: Any, option: str) -> Any:
    """The PEM key of type ``kind`` in ``path`` (private or public, as ``kind`` is)."""
    private = "Private" in kind.__name__
    what = "an unencrypted PEM private key" if private else "a PEM public key"
    try:
        data = path.read_bytes()
        key = (
            serialization.load_pem_private_key(data, None)
            if private
            else serialization.load_pem_public_key(data)
        )
    except (OSError, ValueError, TypeError, UnsupportedAlgorithm) as exc:
        raise click.BadParameter(f"{path}: not {what} ({exc})", param_hint=option) from None
    if not isinstance(key, kind):
        message = f"{path}: a {type(key).__name__}, not a {kind.__name__}"
        raise click.BadParameter(message, param_hint=option)
    if private:
        warn_if_shared(path, option.strip("'"))
    return key


def _session_recorder(audit: AuditLog) -> Callable[[SessionEvent], None]:
    """Log a session change at INFO and audit it (always: it is authentic, and rare)."""
    clock = SystemClock()

    def record(event: SessionEvent) -> None:
        log.info("%s", event)
        audit.append(
            at=clock.wall(), outcome="session", code=event.kind.upper(), warning=None,
            msg_type=None, sender=f"pq:{event.peer}", sender_verified=True,
            msg_id=event.session_id.hex(),
        )  # fmt: skip

    return record


def _run(  # noqa: PLR0917 - the end, its endpoints and its operations options
    end: GroundEnd | VehicleEnd,
    local: str,
    air: str,
    audit_path: str,
    metrics_port: int | None,
    metrics_host: str,
    air_bps: int | None,
) -> None:
    from antireplay.config import AuditConfig  # noqa: PLC0415
    from antireplay.mavlink.endpoints import open_transport, parse_endpoint  # noqa: PLC0415
    from antireplay.mavlink.pq.link import PqLink  # noqa: PLC0415
    from antireplay.wiring import mavlink_auditor, open_audit, serve_metrics  # noqa: PLC0415

    _check_audit_file(Path(audit_path), f"--audit: {_MOVE_ASIDE}")  # before opening anything
    try:
        transports = [open_transport(parse_endpoint(text)) for text in (local, air)]
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    except OSError as exc:
        raise click.ClickException(f"{local} / {air}: {exc.strerror or exc}") from None
    try:
        audit_log = open_audit(AuditConfig(path=audit_path))  # rotated, retained
    except StateFileError as exc:
        _fail(str(exc))
    refusals = mavlink_auditor(audit_log)
    link = PqLink(
        end, *transports, on_reject=refusals, on_session=_session_recorder(audit_log),
        air_bps=air_bps,
    )  # fmt: skip
    if metrics_port is not None:
        try:
            serve_metrics(lambda: pq_metrics(link.counts()), metrics_port, metrics_host)
        except (OSError, ValueError) as exc:  # an unknown host, a busy port, a bad name
            _fail(
                f"--metrics-host {metrics_host} --metrics-port {metrics_port}: cannot serve "
                f"metrics there ({getattr(exc, 'strerror', None) or exc})"
            )
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    done = stop_on_signal()
    link.start()
    side = "fc" if link.name == "vehicle" else "local"  # the vehicle end's local side: the FC
    click.echo(f"mavlink-pq {link.name}: {side} {local}, air {air}", err=True)
    done.wait()
    link.stop()
    refusals.close()  # the folded refusals' summary rows, before the trail closes
    audit_log.close()
    forwarded, dropped = _shown(link.forwarded, side), _shown(link.dropped, side)
    sessions = " ".join(f"{k}={v}" for k, v in sorted(link.sessions.items())) or "none"
    kinds = " ".join(f"{k}={v}" for k, v in sorted(link.counts().airtime.items())) or "none"
    click.echo(
        f"forwarded {forwarded}; dropped {dropped}; sessions {sessions}; "
        f"{link.air_bytes} bytes on air ({kinds})",
        err=True,
    )


def _shown(counts: Mapping[str, int], side: str) -> str:
    """Counts as printed at exit, the local side named ``side`` (the vehicle end's: "fc")."""
    parts = []
    for key, value in sorted(counts.items()):
        name = side + key.removeprefix("local") if key.startswith("local") else key
        parts.append(f"{name}={value}{why(key)}")
    return " ".join(parts) or "none"


@click.group("mavlink-pq")
def mavlink_pq() -> None:
    """Post-quantum MAVLink: a ground end and a vehicle end with any routers between."""


@mavlink_pq.command()
@click.option(
    "--local",
    default="udpin:127.0.0.1:14550",
    show_default=True,
    help="Where ground stations connect.",
)
@click.option("--air", required=True, help="Towards the vehicle (radio, MAVProxy, a router).")
@click.option(
    "--identity",
    default="gcs",
    show_default=True,
    help="The name the vehicle knows this operator by.",
)
@click.option(
    "--signing-key", required=True, type=PEM, help="The operator's ML-DSA-87 private key."
)
@click.option(
    "--vehicle-key", required=True, type=PEM, help="The vehicle's ML-KEM-1024 public key."
)
@click.option(
    "--vehicle-x25519", type=PEM, help="The vehicle's X25519 public key: hybrid handshakes."
)
@click.option(
    "--system-id",
    default=255,
    show_default=True,
    type=click.IntRange(1, 255),
    help="The MAVLink system id of the PQ_CHUNK frames this end sends (a ground station's).",
)
@click.option(
    "--queue-ttl",
    default=5.0,
    show_default=True,
    type=click.FloatRange(0, 600),
    help="Seconds a command waits for a session before it is dropped (counted).",
)
@_operations("ground")
def ground(  # noqa: PLR0917 - one option per knob
    local: str,
    air: str,
    identity: str,
    signing_key: Path,
    vehicle_key: Path,
    vehicle_x25519: Path | None,
    system_id: int,
    queue_ttl: float,
    audit_path: str,
    metrics_port: int | None,
    metrics_host: str,
    air_bps: int | None,
) -> None:
    """The end next to the ground station: opens the session, wraps its peers' messages."""
    from antireplay.mavlink.pq import GroundEnd  # noqa: PLC0415
    from antireplay.pq.session import Initiator  # noqa: PLC0415

    key: mldsa.MLDSA87PrivateKey = _key(signing_key, mldsa.MLDSA87PrivateKey, "'--signing-key'")
    kem: mlkem.MLKEM1024PublicKey = _key(vehicle_key, mlkem.MLKEM1024PublicKey, "'--vehicle-key'")
    hybrid = None
    if vehicle_x25519 is not None:
        hybrid = _key(vehicle_x25519, x25519.X25519PublicKey, "'--vehicle-x25519'")
    try:
        initiator = Initiator(identity, key)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'--identity'") from None
    end = GroundEnd(
        initiator, kem, system_id=system_id, hybrid=hybrid, queue_ttl_s=queue_ttl,
        air_bps=air_bps,
    )  # fmt: skip
    _run(end, local, air, audit_path, metrics_port, metrics_host, air_bps)


@mavlink_pq.command()
@click.option(
    "--fc", required=True, help="The flight controller (serial DEVICE,BAUD, udpout:, ...)."
)
@click.option(
    "--air",
    required=True,
    help="Towards the ground (udpin: learns its peer from authenticated blobs).",
)
@click.option("--kem-key", required=True, type=PEM, help="The vehicle's ML-KEM-1024 private key.")
@click.option(
    "--peer",
    "peers",
    multiple=True,
    required=True,
    metavar="NAME=PEM",
    help="An operator's ML-DSA-87 public key.",
)
@click.option(
    "--x25519-key", type=PEM, help="The vehicle's X25519 private key: hybrid handshakes only."
)
@click.option(
    "--system-id",
    default=1,
    show_default=True,
    type=click.IntRange(1, 255),
    help="The MAVLink system id of the PQ_CHUNK frames this end sends (the vehicle's).",
)
@click.option(
    "--max-sessions",
    default=4,
    show_default=True,
    type=click.IntRange(1, 256),
    help="Sessions held at once (operators, rekeys); a new one evicts the oldest with its keys.",
)
@click.option(
    "--max-age",
    "max_age_s",
    default=10.0,
    show_default=True,
    type=click.FloatRange(min=0.5),
    help="Seconds a command may take from the ground end to here; an older one is refused.",
)
@_operations("vehicle")
def vehicle(  # noqa: PLR0917 - one option per knob
    fc: str,
    air: str,
    kem_key: Path,
    peers: tuple[str, ...],
    x25519_key: Path | None,
    system_id: int,
    max_sessions: int,
    max_age_s: float,
    audit_path: str,
    metrics_port: int | None,
    metrics_host: str,
    air_bps: int | None,
) -> None:
    """The end next to the autopilot: verifies, unwraps, delivers plain MAVLink to it."""
    from antireplay.mavlink.pq import VehicleEnd  # noqa: PLC0415
    from antireplay.pq.session import Responder  # noqa: PLC0415

    kem: mlkem.MLKEM1024PrivateKey = _key(kem_key, mlkem.MLKEM1024PrivateKey, "'--kem-key'")
    registry: dict[str, mldsa.MLDSA87PublicKey] = {}
    for entry in peers:
        name, sep, path = entry.partition("=")
        if not sep or not name or not path:
            raise click.BadParameter(f"{entry!r}: expected NAME=PEM", param_hint="'--peer'")
        registry[name] = _key(Path(path), mldsa.MLDSA87PublicKey, "'--peer'")
    hybrid = None
    if x25519_key is not None:
        hybrid = _key(x25519_key, x25519.X25519PrivateKey, "'--x25519-key'")
    responder = Responder(kem, registry, max_sessions=max_sessions, x25519_key=hybrid)
    end = VehicleEnd(responder, system_id=system_id, max_age_s=max_age_s)
    _run(end, fc, air, audit_path, metrics_port, metrics_host, air_bps)
