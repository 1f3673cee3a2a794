"""``antireplay mavlink-pq ground|vehicle``: the two post-quantum ends as commands.

Registered by :mod:`antireplay.cli`; the pymavlink dialect is imported only when a
command runs.  Each command parses its flags, reads ``--config`` (the ``mavlink_pq:``
block of its end, with ``audit:``, ``audit_space:`` and ``state:``; each flag overrides its
key), calls :func:`~antireplay.wiring.mavlink_pq.open_pq_end` and runs the link until
SIGINT or SIGTERM, then prints the counts.  Keys are PEM files from ``antireplay keygen``
(``--alg ml-dsa-87`` for the operator, ``ml-kem-1024`` and, for the hybrid option,
``x25519`` for the vehicle).  With ``--metrics-port`` the link's counts
(:func:`~antireplay.wiring.metrics.pq_metrics`) are served to Prometheus; ``--air-bps``
paces the air side to the radio's serial rate.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Literal, TypeVar

import click

from antireplay.cli._common import (
    _MOVE_ASIDE,
    _check_audit_file,
    _fail,
    load_with_flags,
    stop_on_signal,
    warn_if_shared,
    why,
)
from antireplay.core.errors import ConfigError, StateFileError

#: Why a PQ end never starts fenced, said in its start line (a router on a new or memory
#: store does start fenced, and says until when): nothing outlives a session here.
NOT_FENCED = (
    "no restart fence: every session's keys are new at its handshake, so nothing a previous "
    "run accepted can be played into it"
)
PEM = click.Path(path_type=Path, dir_okay=False, exists=True)
F = TypeVar("F", bound=Callable[..., Any])


def _operations(end: str) -> Callable[[F], F]:
    """The options every end shares: its config, audit trail, metrics port, air budget."""

    def apply(command: F) -> F:
        for option in (
            click.option(
                "--config", "config_path", type=click.Path(path_type=Path, dir_okay=False),
                default=None, help=f"YAML configuration: the mavlink_pq.{end} block, with "
                "audit:, audit_space: and state: (each flag overrides its key).",
            ),
            click.option(
                "--audit", "audit_path", default=None,
                help="The audit trail: refusals and session changes, rotated and retained "
                f"as audit: says.  [default: audit.path, else .antireplay/mavlink-pq-{end}-"
                "audit.db]",
            ),
            click.option(
                "--metrics-port", type=click.IntRange(0, 65535), default=None,
                help="Serve Prometheus metrics here.",
            ),
            click.option(
                "--metrics-host", default=None,
                help="The address the metrics port binds (0.0.0.0 for a Prometheus on "
                "another host).  [default: 127.0.0.1]",
            ),
            click.option(
                "--air-bps", type=click.IntRange(1_200, 10_000_000), default=None,
                help="The radio's serial rate in baud (57600 for a SiK radio): pace what "
                "goes on air to it, telemetry ahead of long transfers; a failing handshake "
                "takes at most 5 % of it.  Default: unpaced (the 5 % of 57600).",
            ),
        ):  # fmt: skip
            command = option(command)
        return command

    return apply


def _run(
    which: Literal["ground", "vehicle"], config_path: Path | None, flags: dict[str, Any]
) -> None:
    """Read the configuration with ``flags`` (``--option``: (key under the end, value))
    over it, open the end through wiring, run it until a signal, print its counts."""
    from antireplay.wiring.mavlink_pq import open_pq_end, pq_audit_path  # noqa: PLC0415
    from antireplay.wiring.metrics import pq_metrics, serve_metrics, trail_metrics  # noqa: PLC0415

    at = f"mavlink_pq.{which}"
    config = load_with_flags(config_path, {
        "audit.path" if key == "audit" else f"{at}.{key}": (flag, value)
        for flag, (key, value) in flags.items()
    })  # fmt: skip
    _warn_private_keys(getattr(config.mavlink_pq, which), at, flags)
    trail = pq_audit_path(config, which)
    _check_audit_file(Path(trail), f"--audit: {_MOVE_ASIDE}")  # before opening anything
    try:
        parts = open_pq_end(config, which, trail)
    except (ConfigError, StateFileError) as exc:
        _fail(str(exc))
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    except OSError as exc:
        _fail(str(exc.strerror or exc))  # names the endpoint
    link, metrics = parts.link, getattr(config.mavlink_pq, which).metrics
    if metrics.port is not None:
        try:
            serve_metrics(
                lambda: [
                    *pq_metrics(link.counts()),
                    *trail_metrics(f"mavlink-pq {which}", parts.audit, parts.space),
                ],
                metrics.port, metrics.host,
            )  # fmt: skip
        except (OSError, ValueError) as exc:  # an unknown host, a busy port, a bad name
            _fail(
                f"--metrics-host {metrics.host} --metrics-port {metrics.port}: cannot serve "
                f"metrics there ({getattr(exc, 'strerror', None) or exc})"
            )
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    done = stop_on_signal()
    link.start()
    side = "fc" if link.name == "vehicle" else "local"  # the vehicle end's local side: the FC
    click.echo(
        f"mavlink-pq {link.name}: {side} {parts.local}, air {parts.air}; {NOT_FENCED}", err=True
    )
    done.wait()
    parts.close()
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


#: The private keys of each end's section (a public key may be shared).
_PRIVATE_KEYS = ("signing_key", "kem_key", "x25519_key")


def _warn_private_keys(section: Any, at: str, flags: dict[str, Any]) -> None:
    """One warning line for each private key file (read by wiring) that group or others may
    read, named by its flag if one gave it, else by its key."""
    given = {key: flag for flag, (key, value) in flags.items() if value is not None}
    for key in _PRIVATE_KEYS:
        path = getattr(section, key, None)
        if path is not None:
            warn_if_shared(Path(path), given.get(key, f"{at}.{key}"))


def _operation_flags(
    audit_path: str | None,
    metrics_port: int | None,
    metrics_host: str | None,
    air_bps: int | None,
) -> dict[str, Any]:
    return {
        "--audit": ("audit", audit_path), "--metrics-port": ("metrics.port", metrics_port),
        "--metrics-host": ("metrics.host", metrics_host), "--air-bps": ("air_bps", air_bps),
    }  # fmt: skip


@click.group("mavlink-pq")
def mavlink_pq() -> None:
    """Post-quantum MAVLink: a ground end and a vehicle end with any routers between."""


@mavlink_pq.command()
@click.option(
    "--local",
    default=None,
    help="Where ground stations connect.  [default: udpin:127.0.0.1:14550]",
)
@click.option("--air", default=None, help="Towards the vehicle (radio, MAVProxy, a router).")
@click.option(
    "--identity",
    default=None,
    help="The name the vehicle knows this operator by.  [default: gcs]",
)
@click.option("--signing-key", type=PEM, help="The operator's ML-DSA-87 private key.")
@click.option("--vehicle-key", type=PEM, help="The vehicle's ML-KEM-1024 public key.")
@click.option(
    "--vehicle-x25519", type=PEM, help="The vehicle's X25519 public key: hybrid handshakes."
)
@click.option(
    "--system-id",
    default=None,
    type=click.IntRange(1, 255),
    help="The MAVLink system id of the PQ_CHUNK frames this end sends (a ground station's).  "
    "[default: 255]",
)
@click.option(
    "--queue-ttl",
    default=None,
    type=click.FloatRange(0, 600),
    help="Seconds a command waits for a session before it is dropped (counted).  [default: 5]",
)
@_operations("ground")
def ground(  # noqa: PLR0917 - one option per knob
    local: str | None,
    air: str | None,
    identity: str | None,
    signing_key: Path | None,
    vehicle_key: Path | None,
    vehicle_x25519: Path | None,
    system_id: int | None,
    queue_ttl: float | None,
    config_path: Path | None,
    audit_path: str | None,
    metrics_port: int | None,
    metrics_host: str | None,
    air_bps: int | None,
) -> None:
    """The end next to the ground station: opens the session, wraps its peers' messages."""
    _run("ground", config_path, {
        "--local": ("local", local), "--air": ("air", air), "--identity": ("identity", identity),
        "--signing-key": ("signing_key", _text(signing_key)),
        "--vehicle-key": ("vehicle_key", _text(vehicle_key)),
        "--vehicle-x25519": ("vehicle_x25519", _text(vehicle_x25519)),
        "--system-id": ("system_id", system_id), "--queue-ttl": ("queue_ttl_s", queue_ttl),
        **_operation_flags(audit_path, metrics_port, metrics_host, air_bps),
    })  # fmt: skip


@mavlink_pq.command()
@click.option(
    "--fc", default=None, help="The flight controller (serial DEVICE,BAUD, udpout:, ...)."
)
@click.option(
    "--air",
    default=None,
    help="Towards the ground (udpin: learns its peer from authenticated blobs).",
)
@click.option("--kem-key", type=PEM, help="The vehicle's ML-KEM-1024 private key.")
@click.option(
    "--peer",
    "peers",
    multiple=True,
    metavar="NAME=PEM",
    help="An operator's ML-DSA-87 public key (one or more).",
)
@click.option(
    "--x25519-key", type=PEM, help="The vehicle's X25519 private key: hybrid handshakes only."
)
@click.option(
    "--system-id",
    default=None,
    type=click.IntRange(1, 255),
    help="The MAVLink system id of the PQ_CHUNK frames this end sends (the vehicle's).  "
    "[default: 1]",
)
@click.option(
    "--max-sessions",
    default=None,
    type=click.IntRange(1, 256),
    help="Sessions held at once (operators, rekeys); a new one evicts the oldest with its "
    "keys.  [default: 4]",
)
@click.option(
    "--max-age",
    "max_age_s",
    default=None,
    type=click.FloatRange(min=0.5),
    help="Seconds a command may take from the ground end to here; an older one is refused.  "
    "[default: 10]",
)
@_operations("vehicle")
def vehicle(  # noqa: PLR0917 - one option per knob
    fc: str | None,
    air: str | None,
    kem_key: Path | None,
    peers: tuple[str, ...],
    x25519_key: Path | None,
    system_id: int | None,
    max_sessions: int | None,
    max_age_s: float | None,
    config_path: Path | None,
    audit_path: str | None,
    metrics_port: int | None,
    metrics_host: str | None,
    air_bps: int | None,
) -> None:
    """The end next to the autopilot: verifies, unwraps, delivers plain MAVLink to it."""
    registry: dict[str, str] = {}
    for entry in peers:
        name, sep, path = entry.partition("=")
        if not sep or not name or not path:
            raise click.BadParameter(f"{entry!r}: expected NAME=PEM", param_hint="'--peer'")
        registry[name] = path
    _run("vehicle", config_path, {
        "--fc": ("fc", fc), "--air": ("air", air), "--kem-key": ("kem_key", _text(kem_key)),
        "--peer": ("peers", registry or None), "--x25519-key": ("x25519_key", _text(x25519_key)),
        "--system-id": ("system_id", system_id), "--max-sessions": ("max_sessions", max_sessions),
        "--max-age": ("max_age_s", max_age_s),
        **_operation_flags(audit_path, metrics_port, metrics_host, air_bps),
    })  # fmt: skip


def _text(path: Path | None) -> str | None:
    return None if path is None else str(path)
