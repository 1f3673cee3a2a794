"""``mavlink-router`` (first name ``mavlink-proxy``) and ``mavlink-sim``.

``mavlink-router`` parses its flags, reads ``--config`` (the ``mavlink:`` section with
``audit:``, ``audit_space:`` and ``state:``; each flag overrides its key) and calls
:func:`~antireplay.wiring.mavlink.open_router`; then it waits for a signal.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

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
from antireplay.cli.mavlink_keys import reload_on_sighup
from antireplay.core.counters import DEFAULT_WINDOW
from antireplay.core.errors import ConfigError, ReplayAttackError, StateFileError

if TYPE_CHECKING:
    from antireplay.config import MavlinkConfig
    from antireplay.wiring.mavlink import RouterParts


def _signing_key(path: Path) -> bytes:
    """A key file as ``--key-file`` reads it (:func:`~antireplay.wiring.mavlink.read_key_file`)."""
    from antireplay.wiring.mavlink import read_key_file  # noqa: PLC0415

    try:
        key = read_key_file(str(path), "--key")
    except ConfigError as exc:
        raise click.BadParameter(str(exc)) from None
    warn_if_shared(path, "--key")
    return key


@click.command("mavlink-router")
@click.option(
    "--config",
    "config_path",
    type=click.Path(path_type=Path, dir_okay=False),
    default=None,
    help="YAML configuration: the mavlink: section, with audit:, audit_space: and state: "
    "(each flag overrides its key).",
)
@click.option(
    "--vehicle",
    multiple=True,
    help="Vehicle side: a serial DEVICE,BAUD, udpin:, udpout:, tcp: or tcpin:HOST:PORT "
    "(frames must verify with the vehicle key).",
)
@click.option(
    "--ground",
    multiple=True,
    help="Untrusted ground link (radio, LTE, a GCS): its frames must verify; routes and "
    "peers are learned only from frames that do.",
)
@click.option(
    "--trusted",
    multiple=True,
    help="Trusted local tool that cannot sign (mavros, BlueOS, a script): its frames are "
    "signed on its behalf.  Loopback or a wired serial port only: a serial telemetry radio "
    "(SiK/RFD) or Bluetooth serial is not local and must not be --trusted.",
)
@click.option(
    "--trust-network",
    multiple=True,
    metavar="ENDPOINT",
    help="Acknowledge a --trusted endpoint that is not loopback or a serial device (exactly "
    "as given): anyone who reaches it commands the vehicle with its key.",
)
@click.option(
    "--listen", default=None, help="Shorthand for --ground udpin:HOST:PORT (udp:HOST:PORT)."
)
@click.option(
    "--forward", default=None, help="Shorthand for --vehicle udpout:HOST:PORT (udp:HOST:PORT)."
)
@click.option(
    "--key-file",
    type=click.Path(exists=True, path_type=Path),
    default=None,
    help="The default link key: 32 raw bytes or 64 hex digits.",
)
@click.option(
    "--passphrase-env",
    default=None,
    metavar="VAR",
    help="The default link key is SHA-256 of this environment variable's passphrase (as "
    "MAVProxy, QGC and Mission Planner derive it).",
)
@click.option(
    "--signing-keys",
    type=click.Path(exists=True, path_type=Path),
    default=None,
    help="Per-link passphrases in MAVProxy's signing.keys format: lines 'ENDPOINT PASSPHRASE'.",
)
@click.option(
    "--system-id",
    type=click.IntRange(1, 255),
    default=None,
    help="This vehicle's system id (ArduPilot's and PX4's default is 1): frames addressed "
    "elsewhere, and frames from it reflected back from a ground link, are refused.  "
    "[default: 1]",
)
@click.option(
    "--store",
    "store_spec",
    default=None,
    help="Where each stream's last timestamp is kept (memory, sqlite:PATH, redis://...).  "
    "[default: sqlite:.antireplay/mavlink.db]",
)
@click.option(
    "--audit",
    "audit_path",
    default=None,
    help="The audit trail of refusals and first authentications (SQLite), rotated and "
    "retained as audit: says.  [default: audit.path, else .antireplay/mavlink-audit.db]",
)
@click.option(
    "--metrics-port",
    type=click.IntRange(0, 65535),
    default=None,
    help="Serve Prometheus metrics here.",
)
@click.option(
    "--metrics-host",
    default=None,
    help="The address the metrics port binds (0.0.0.0 for a Prometheus on another host).  "
    "[default: 127.0.0.1]",
)
@click.option(
    "--allow-unsigned",
    multiple=True,
    help="[to-vehicle:|from-vehicle:]MESSAGE[:v1]: a message (name or id) taken unsigned, in "
    "one direction or both; ':v1' takes it as a MAVLink v1 frame too.",
)
@click.option(
    "--reorder-window",
    type=click.IntRange(0, DEFAULT_WINDOW),
    default=None,
    help="Accept out-of-order timestamps within this many (0: strictly increasing).  [default: 0]",
)
@click.option(
    "--max-forward-s",
    type=click.FloatRange(0, min_open=True),
    default=None,
    help="Refuse timestamps more than this far ahead of the router's clock.  [default: 60]",
)
@click.option(
    "--new-stream-max-age-s",
    type=click.FloatRange(0, min_open=True),
    default=None,
    help="A new stream's first timestamp may be this far behind the router's clock (the "
    "MAVLink 60 s rule; raise it for slow links).  [default: 60]",
)
@click.option(
    "--sign-link-id",
    type=click.IntRange(0, 255),
    default=None,
    help="The link id in the signatures the router makes (on behalf of trusted tools).  "
    "[default: 251]",
)
@click.option(
    "--write-through/--no-write-through",
    default=None,
    help="Write every accepted timestamp to the store before forwarding (several routers "
    "active at once on one store); default: persist every second behind a lease and a "
    "restart fence.",
)
def mavlink_router(  # noqa: PLR0917 - one option per knob
    config_path: Path | None,
    vehicle: tuple[str, ...],
    ground: tuple[str, ...],
    trusted: tuple[str, ...],
    trust_network: tuple[str, ...],
    listen: str | None,
    forward: str | None,
    key_file: Path | None,
    passphrase_env: str | None,
    signing_keys: Path | None,
    system_id: int | None,
    store_spec: str | None,
    audit_path: str | None,
    metrics_port: int | None,
    metrics_host: str | None,
    allow_unsigned: tuple[str, ...],
    reorder_window: int | None,
    max_forward_s: float | None,
    new_stream_max_age_s: float | None,
    sign_link_id: int | None,
    write_through: bool | None,
) -> None:
    """Route MAVLink between vehicle, trusted and ground endpoints; forward only what the
    guards accept (also answers to its first name, mavlink-proxy)."""
    import logging  # noqa: PLC0415
    import signal  # noqa: PLC0415

    # A SIGHUP during start-up waits (blocked, pending) for the reload handler: never lost,
    # never the default action (exit).
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGHUP})

    from antireplay.wiring.leaves import trail_path  # noqa: PLC0415
    from antireplay.wiring.mavlink import (  # noqa: PLC0415
        ROUTER_AUDIT,
        fence_notice,
        open_router,
    )
    from antireplay.wiring.metrics import (  # noqa: PLC0415
        router_metrics,
        serve_metrics,
        trail_metrics,
    )

    grounds = [*ground, *([_udp_shorthand(listen, "udpin", "--listen")] if listen else [])]
    vehicles = [*vehicle, *([_udp_shorthand(forward, "udpout", "--forward")] if forward else [])]
    config = load_with_flags(config_path, {
        "mavlink.vehicle": ("--vehicle", tuple(vehicles)),
        "mavlink.ground": ("--ground", tuple(grounds)),
        "mavlink.trusted": ("--trusted", trusted),
        "mavlink.trust_network": ("--trust-network", trust_network),
        "mavlink.key_file": ("--key-file", key_file and str(key_file)),
        "mavlink.passphrase_env": ("--passphrase-env", passphrase_env),
        "mavlink.signing_keys": ("--signing-keys", signing_keys and str(signing_keys)),
        "mavlink.system_id": ("--system-id", system_id),
        "mavlink.store": ("--store", store_spec),
        "audit.path": ("--audit", audit_path),
        "mavlink.metrics.port": ("--metrics-port", metrics_port),
        "mavlink.metrics.host": ("--metrics-host", metrics_host),
        "mavlink.allow_unsigned": ("--allow-unsigned", allow_unsigned),
        "mavlink.reorder_window": ("--reorder-window", reorder_window),
        "mavlink.max_forward_s": ("--max-forward-s", max_forward_s),
        "mavlink.new_stream_max_age_s": ("--new-stream-max-age-s", new_stream_max_age_s),
        "mavlink.sign_link_id": ("--sign-link-id", sign_link_id),
        "mavlink.write_through": ("--write-through", write_through),
    })  # fmt: skip
    section = config.mavlink
    for name, flag, given in (("key_file", "--key-file", key_file),
                              ("signing_keys", "--signing-keys", signing_keys)):  # fmt: skip
        secret = getattr(section, name)
        if secret is not None:  # read by wiring; a shared one is the operator's to hear of
            warn_if_shared(Path(secret), flag if given is not None else f"mavlink.{name}")
    trail = trail_path(config, ROUTER_AUDIT)
    _check_audit_file(Path(trail), f"--audit: {_MOVE_ASIDE}")  # before opening anything
    try:
        parts = open_router(config, trail)
    except (ConfigError, StateFileError) as exc:
        _fail(str(exc))
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    except OSError as exc:
        _fail(str(exc.strerror or exc))  # names the endpoint
    except ReplayAttackError as exc:
        _fail(f"--store {section.store}: {exc}")
    metrics = section.metrics
    if metrics.port is not None:
        try:
            serve_metrics(
                lambda: [
                    *router_metrics(parts.router),
                    *trail_metrics(
                        "mavlink-router", parts.audit, parts.space, parts.store,
                        lambda: fence_notice(parts.router, parts.store, time.time()),
                    ),
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
    keys_said = reload_on_sighup(parts.router, section)  # before start: SIGHUP never kills
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGHUP})  # a pending one reloads now
    try:
        parts.router.start()  # claims each guard's lease, waiting out a crashed run's (seconds)
    except ReplayAttackError as exc:
        _fail(f"--store {section.store}: {exc}")
    click.echo(_start_line(parts, section) + keys_said)  # one line
    done.wait()
    parts.close()
    stats = parts.router.stats
    forwarded = ", ".join(f"{k} {v}" for k, v in sorted(stats.forwarded.items())) or "none"
    dropped = ", ".join(f"{k} {v}{why(k)}" for k, v in sorted(stats.dropped.items())) or "none"
    click.echo(f"forwarded {forwarded}; dropped {dropped}", err=True)


def _start_line(parts: RouterParts, section: MavlinkConfig) -> str:
    """The router's one start line: its endpoints, the trusted ones acknowledged on the
    network, and its restart fence while one lies ahead (until when, why, what removes it)."""
    from antireplay.wiring.mavlink import fence_notice  # noqa: PLC0415

    roles = ", ".join(f"{role} {text}" for role, text, _ in parts.endpoints)
    said = [f"mavlink-router {roles} (system id {section.system_id})"]
    if section.trust_network:
        said.append(
            "trusted on the network, acknowledged (--trust-network): "
            f"{', '.join(section.trust_network)} (anyone who reaches it commands the vehicle)"
        )
    fenced = fence_notice(parts.router, parts.store, time.time())
    if fenced is not None:  # a memory store, a new or lost state, a spike not yet passed
        said.append(fenced)
    return "; ".join(said)


def _udp_shorthand(spec: str, kind: str, option: str) -> str:
    """``--listen``/``--forward``: ``udp:HOST:PORT`` (or ``KIND:HOST:PORT``) as ``KIND:...``."""
    scheme, _, rest = spec.partition(":")
    host, _, port = rest.rpartition(":")
    if (
        scheme not in {"udp", kind}
        or not host
        or not (port.isascii() and port.isdigit())
        or int(port) > 65535
    ):
        raise click.BadParameter(
            f"{spec!r}: expected udp:HOST:PORT with PORT 0..65535", param_hint=f"'{option}'"
        )
    return f"{kind}:{rest}"


def _sim_key(value: str | None, passphrase_env: str | None) -> bytes | None:
    """``--key``: 64 hex digits, or a key file as ``--key-file`` reads it; or a passphrase;
    neither: no key (signing off until a SETUP_SIGNING gives one)."""
    from antireplay.mavlink import passphrase_key  # noqa: PLC0415

    if value is not None and passphrase_env is not None:
        raise click.UsageError("give --key or --passphrase-env, not both")
    if value is None and passphrase_env is None:
        return None
    if passphrase_env is not None:
        phrase = os.environ.get(passphrase_env)
        if not phrase:
            raise click.BadParameter(
                f"{passphrase_env} is not set", param_hint="'--passphrase-env'"
            )
        return passphrase_key(phrase)
    assert value is not None
    try:
        return bytes.fromhex(value) if len(value) == 64 else _signing_key(Path(value))
    except ValueError:
        return _signing_key(Path(value))


@click.command("mavlink-sim")
@click.option(
    "--udp",
    default="127.0.0.1:14555",
    show_default=True,
    metavar="HOST:PORT",
    help="Send to this address (the router's --vehicle udpin:HOST:PORT); answers come back "
    "to the simulator's own port.",
)
@click.option(
    "--pty",
    is_flag=True,
    help="Use a pseudo-terminal instead of UDP; its path is printed (the router's "
    "--vehicle PATH,115200).",
)
@click.option(
    "--key",
    default=None,
    help="The vehicle's signing key: 64 hex digits, or a key file (32 raw bytes or 64 hex); "
    "none: signing off until a SETUP_SIGNING gives one.",
)
@click.option(
    "--passphrase-env",
    default=None,
    metavar="VAR",
    help="Or the key as SHA-256 of this environment variable's passphrase.",
)
@click.option(
    "--system-id",
    type=click.IntRange(1, 255),
    default=1,
    show_default=True,
    help="The simulated vehicle's system id.",
)
@click.option(
    "--rate",
    type=click.FloatRange(0.1, 50),
    default=4.0,
    show_default=True,
    help="HEARTBEAT and ATTITUDE per second.",
)
@click.option("--armed", is_flag=True, help="Start armed (a SETUP_SIGNING is ignored while armed).")
def mavlink_sim(  # noqa: PLR0917 - one option per knob
    udp: str,
    pty: bool,
    key: str | None,
    passphrase_env: str | None,
    system_id: int,
    rate: float,
    armed: bool,
) -> None:
    """A simulated signing vehicle: MAVLink 2 telemetry, and a COMMAND_ACK for each
    COMMAND_LONG that verifies; takes SETUP_SIGNING as ArduPilot does (never while armed);
    prints its counts when stopped (SIGTERM or Ctrl-C)."""
    from antireplay.mavlink.sim import SimVehicle  # noqa: PLC0415

    secret = _sim_key(key, passphrase_env)
    host, _, port = udp.rpartition(":")
    if not host or not (port.isascii() and port.isdigit()) or not 0 < int(port) < 65536:
        raise click.BadParameter(f"{udp!r}: expected HOST:PORT", param_hint="'--udp'")
    try:
        sim = SimVehicle(
            secret, system_id=system_id, udp=(host, int(port)), pty=pty, rate_hz=rate, armed=armed
        )
    except OSError as exc:
        _fail(f"--udp {udp}: {exc.strerror or exc}")
    click.echo(f"mavlink-sim system {system_id}: router option --vehicle {sim.where}")
    done = stop_on_signal()
    try:
        sim.run(done)
    finally:
        sim.close()
    counts = ", ".join(f"{k} {v}" for k, v in sorted(sim.counts.items()))
    click.echo(f"sent and received: {counts or 'nothing'}", err=True)
