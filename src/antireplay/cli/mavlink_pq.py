"""``antireplay mavlink-pq ground|vehicle``: the two post-quantum ends as commands.

Registered by :mod:`antireplay.cli`; it lives outside :mod:`antireplay.mavlink` so that
the pymavlink dialect is imported only when a command runs.
Keys are PEM files from ``antireplay keygen`` (``--alg ml-dsa-87`` for the operator,
``ml-kem-1024`` and, for the hybrid option, ``x25519`` for the vehicle).  Each command
runs one :class:`~antireplay.mavlink.pq.link.PqLink` until SIGINT or SIGTERM, logs
refusals through a :class:`~antireplay.audit.RefusalAuditor` (at most ``LOG_PER_S``
lines a second; the rest are counted) and prints the counts when it stops.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
from cryptography.exceptions import UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import mldsa, mlkem, x25519

from antireplay.audit.refusals import RefusalAuditor
from antireplay.cli._common import stop_on_signal

if TYPE_CHECKING:
    from antireplay.mavlink.pq import GroundEnd, VehicleEnd

LOG_PER_S = 10.0
log = logging.getLogger("antireplay.mavlink.pq")
PEM = click.Path(path_type=Path, dir_okay=False, exists=True)


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
    return key


def _run(end: GroundEnd | VehicleEnd, local: str, air: str, what: str) -> None:
    from antireplay.mavlink.endpoints import open_transport, parse_endpoint  # noqa: PLC0415
    from antireplay.mavlink.pq.link import PqLink  # noqa: PLC0415
    from antireplay.mavlink.router import Refusal  # noqa: PLC0415

    try:
        transports = [open_transport(parse_endpoint(text)) for text in (local, air)]
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    except OSError as exc:
        raise click.ClickException(f"{local} / {air}: {exc.strerror or exc}") from None
    auditor = RefusalAuditor(per_s=LOG_PER_S, log=log)

    def report(refusal: Refusal) -> None:
        auditor.record(code=refusal.code, sender=None, sender_verified=False, line=str(refusal))

    link = PqLink(end, *transports, on_reject=report)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    done = stop_on_signal()
    link.start()
    click.echo(f"mavlink-pq {what}: local {local}, air {air}", err=True)
    done.wait()
    link.stop()
    forwarded = " ".join(f"{k}={v}" for k, v in sorted(link.forwarded.items())) or "none"
    dropped = " ".join(f"{k}={v}" for k, v in sorted(link.dropped.items())) or "none"
    click.echo(
        f"forwarded {forwarded}; dropped {dropped}; {link.air_bytes} bytes on air; "
        f"{auditor.folded_total} refusals not logged",
        err=True,
    )


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
@click.option("--system-id", default=255, show_default=True, type=click.IntRange(1, 255))
@click.option(
    "--queue-ttl",
    default=5.0,
    show_default=True,
    type=click.FloatRange(0, 600),
    help="Seconds a command waits for a session before it is dropped (counted).",
)
def ground(  # noqa: PLR0917 - one option per knob
    local: str,
    air: str,
    identity: str,
    signing_key: Path,
    vehicle_key: Path,
    vehicle_x25519: Path | None,
    system_id: int,
    queue_ttl: float,
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
    end = GroundEnd(initiator, kem, system_id=system_id, hybrid=hybrid, queue_ttl_s=queue_ttl)
    _run(end, local, air, "ground")


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
@click.option("--system-id", default=1, show_default=True, type=click.IntRange(1, 255))
@click.option("--max-sessions", default=4, show_default=True, type=click.IntRange(1, 256))
def vehicle(  # noqa: PLR0917 - one option per knob
    fc: str,
    air: str,
    kem_key: Path,
    peers: tuple[str, ...],
    x25519_key: Path | None,
    system_id: int,
    max_sessions: int,
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
    _run(VehicleEnd(responder, system_id=system_id), fc, air, "vehicle")
