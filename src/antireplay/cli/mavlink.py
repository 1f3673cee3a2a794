"""``mavlink-router`` (first name ``mavlink-proxy``): the signing MAVLink router."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import click

from antireplay.core.counters import DEFAULT_WINDOW
from antireplay.core.errors import ConfigError, ReplayAttackError, StateFileError
from antireplay.wiring import Allowed, stop_router

if TYPE_CHECKING:
    from antireplay.mavlink import Role

from antireplay.cli import _common
from antireplay.cli._common import _MOVE_ASIDE, _check_audit_file, _fail, stop_on_signal, why


def _signing_key(path: Path) -> bytes:
    """The link key: exactly 32 raw bytes (taken as they are: a raw key may begin or end
    with a whitespace byte), or 64 hex characters with optional surrounding whitespace."""
    try:
        raw = _common.read_secret(path, "--key-file")
    except OSError as exc:
        raise click.BadParameter(f"{path}: unreadable ({exc.strerror})") from None
    if len(raw) == 32:
        return raw
    text = raw.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except ValueError:
            pass
    raise click.BadParameter(f"{path}: not a MAVLink signing key (32 raw bytes or 64 hex digits)")


def _signing_keys(path: Path | None) -> dict[str, str]:
    """MAVProxy's ``signing.keys``: lines ``ENDPOINT PASSPHRASE`` (endpoint as typed)."""
    if path is None:
        return {}
    try:
        lines = _common.read_secret(path, "--signing-keys").decode().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise click.BadParameter(f"{path}: unreadable ({exc})") from None
    found = {}
    for line in lines:
        words = line.split()
        if len(words) == 2:
            found[words[0].lower()] = words[1]
    return found


def _link_key(endpoint: str, keys: dict[str, str], default: bytes | None) -> bytes:
    """A link's key: its passphrase in the signing-keys file (matched as MAVProxy matches:
    the whole string, or ``HOST:PORT`` against ``PROTO:HOST:PORT``), else the default."""
    from antireplay.mavlink import passphrase_key  # noqa: PLC0415

    text = endpoint.lower()
    host_port = text.partition(":")[2] if text.count(":") == 2 else None
    passphrase = keys.get(text) or (keys.get(host_port) if host_port else None)
    if passphrase is not None:
        return passphrase_key(passphrase)
    if default is None:
        raise click.BadParameter(
            f"{endpoint}: no key (give --key-file, --passphrase-env or a --signing-keys entry)"
        )
    return default


def _allowed(entries: tuple[str, ...]) -> tuple[Allowed, Allowed]:
    """``--allow-unsigned [to-vehicle:|from-vehicle:]MESSAGE[:v1]`` entries, per direction."""
    from pymavlink.dialects.v20 import ardupilotmega as dialect  # noqa: PLC0415

    sets: dict[str, tuple[set[int], set[int]]] = {
        "to-vehicle": (set(), set()),
        "from-vehicle": (set(), set()),
    }
    for entry in entries:
        parts = entry.split(":")
        directions = list(sets)
        if parts[0].lower() in sets:
            directions = [parts.pop(0).lower()]
        v1 = len(parts) == 2 and parts[1].lower() == "v1"
        name = parts[0] if len(parts) == 1 or v1 else ""
        msgid = (
            int(name)
            if name.isdigit()
            else getattr(dialect, f"MAVLINK_MSG_ID_{name.upper()}", None)
        )
        if msgid is None or not 0 <= msgid < 2**24:
            raise click.BadParameter(
                f"{entry!r}: expected [to-vehicle:|from-vehicle:]MESSAGE[:v1], MESSAGE a name "
                "(RADIO_STATUS) or an id",
                param_hint="'--allow-unsigned'",
            )
        for direction in directions:
            sets[direction][0].add(msgid)
            if v1:
                sets[direction][1].add(msgid)
    to_vehicle, from_vehicle = (
        Allowed(frozenset(unsigned), frozenset(v1)) for unsigned, v1 in sets.values()
    )
    return to_vehicle, from_vehicle


def _router_endpoints(  # noqa: PLR0917 - the endpoint and key options, as given
    vehicle: tuple[str, ...],
    ground: tuple[str, ...],
    trusted: tuple[str, ...],
    listen: str | None,
    forward: str | None,
    key_file: Path | None,
    passphrase_env: str | None,
    signing_keys: Path | None,
) -> list[tuple[Role, str, bytes | None]]:
    """``(role, connection string, key)`` for every endpoint the options name."""
    from antireplay.mavlink import Role, passphrase_key  # noqa: PLC0415

    grounds = [*ground, *([_udp_shorthand(listen, "udpin", "--listen")] if listen else [])]
    vehicles = [*vehicle, *([_udp_shorthand(forward, "udpout", "--forward")] if forward else [])]
    if not vehicles:
        raise click.UsageError("give at least one --vehicle (or --forward)")
    default = _signing_key(key_file) if key_file is not None else None
    if passphrase_env is not None:
        if default is not None:
            raise click.UsageError("give --key-file or --passphrase-env, not both")
        phrase = os.environ.get(passphrase_env)
        if not phrase:
            raise click.BadParameter(
                f"{passphrase_env} is not set", param_hint="'--passphrase-env'"
            )
        default = passphrase_key(phrase)
    keys = _signing_keys(signing_keys)
    endpoints: list[tuple[Role, str, bytes | None]] = [
        (Role.VEHICLE, text, _link_key(text, keys, default)) for text in vehicles
    ]
    endpoints += [(Role.GROUND, text, _link_key(text, keys, default)) for text in grounds]
    endpoints += [(Role.TRUSTED, text, None) for text in trusted]
    return endpoints


@click.command("mavlink-router")
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
    "signed on its behalf.",
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
    default=1,
    show_default=True,
    help="This vehicle's system id (ArduPilot's and PX4's default is 1): frames addressed "
    "elsewhere, and frames from it reflected back from a ground link, are refused.",
)
@click.option(
    "--store",
    "store_spec",
    default="sqlite:.antireplay/mavlink.db",
    show_default=True,
    help="Where each stream's last timestamp is kept (memory, sqlite:PATH, redis://...).",
)
@click.option(
    "--audit",
    "audit_path",
    default=".antireplay/mavlink-audit.db",
    show_default=True,
    help="The audit trail of refusals and first authentications (SQLite).",
)
@click.option(
    "--metrics-port",
    type=click.IntRange(0, 65535),
    default=None,
    help="Serve Prometheus metrics here.",
)
@click.option(
    "--metrics-host",
    default="127.0.0.1",
    show_default=True,
    help="The address the metrics port binds (0.0.0.0 for a Prometheus on another host).",
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
    default=0,
    show_default=True,
    help="Accept out-of-order timestamps within this many (0: strictly increasing).",
)
@click.option(
    "--max-forward-s",
    type=click.FloatRange(0, min_open=True),
    default=60.0,
    show_default=True,
    help="Refuse timestamps more than this far ahead of the router's clock.",
)
@click.option(
    "--new-stream-max-age-s",
    type=click.FloatRange(0, min_open=True),
    default=60.0,
    show_default=True,
    help="A new stream's first timestamp may be this far behind the router's clock (the "
    "MAVLink 60 s rule; raise it for slow links).",
)
@click.option(
    "--sign-link-id",
    type=click.IntRange(0, 255),
    default=251,
    show_default=True,
    help="The link id in the signatures the router makes (on behalf of trusted tools).",
)
@click.option(
    "--write-through",
    is_flag=True,
    help="Write every accepted timestamp to the store before forwarding (several routers "
    "active at once on one store); default: persist every second behind a lease and a "
    "restart fence.",
)
def mavlink_router(  # noqa: PLR0917 - one option per knob
    vehicle: tuple[str, ...],
    ground: tuple[str, ...],
    trusted: tuple[str, ...],
    listen: str | None,
    forward: str | None,
    key_file: Path | None,
    passphrase_env: str | None,
    signing_keys: Path | None,
    system_id: int,
    store_spec: str,
    audit_path: str,
    metrics_port: int | None,
    metrics_host: str,
    allow_unsigned: tuple[str, ...],
    reorder_window: int,
    max_forward_s: float,
    new_stream_max_age_s: float,
    sign_link_id: int,
    write_through: bool,
) -> None:
    """Route MAVLink between vehicle, trusted and ground endpoints; forward only what the
    guards accept (also answers to its first name, mavlink-proxy)."""
    import logging  # noqa: PLC0415

    from antireplay.config import AuditConfig  # noqa: PLC0415
    from antireplay.state import open_store  # noqa: PLC0415
    from antireplay.wiring import (  # noqa: PLC0415
        RouterOptions,
        build_mavlink_router,
        open_audit,
        serve_router_metrics,
    )

    endpoints = _router_endpoints(
        vehicle, ground, trusted, listen, forward, key_file, passphrase_env, signing_keys
    )
    to_vehicle, from_vehicle = _allowed(allow_unsigned)
    options = RouterOptions(
        system_id, to_vehicle, from_vehicle, reorder_window, write_through, max_forward_s,
        new_stream_max_age_s, sign_link_id,
    )  # fmt: skip
    _check_audit_file(Path(audit_path), f"--audit: {_MOVE_ASIDE}")  # before opening anything
    try:
        audit_log = open_audit(AuditConfig(path=audit_path))  # rotated, retained, with a spill
    except StateFileError as exc:
        _fail(str(exc))
    try:
        store = open_store(store_spec)
    except ConfigError as exc:
        raise click.BadParameter(f"{store_spec!r}: {exc.allowed}", param_hint="'--store'") from None
    except StateFileError as exc:
        _fail(str(exc))
    try:
        router = build_mavlink_router(endpoints, store, audit_log, options)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    except OSError as exc:
        _fail(str(exc.strerror or exc))  # names the endpoint
    except ReplayAttackError as exc:
        _fail(f"--store {store_spec}: {exc}")
    if metrics_port is not None:
        try:
            serve_router_metrics(router, metrics_port, metrics_host)
        except (OSError, ValueError) as exc:  # an unknown host, a busy port, a bad name
            _fail(
                f"--metrics-host {metrics_host} --metrics-port {metrics_port}: cannot serve "
                f"metrics there ({getattr(exc, 'strerror', None) or exc})"
            )
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    done = stop_on_signal()
    try:
        router.start()  # claims each guard's lease, waiting out a crashed run's (seconds)
    except ReplayAttackError as exc:
        _fail(f"--store {store_spec}: {exc}")
    roles = ", ".join(f"{role} {text}" for role, text, _ in endpoints)
    click.echo(f"mavlink-router {roles} (system id {system_id})")  # one line, never wrapped
    done.wait()
    stop_router(router)
    audit_log.close()
    store.close()
    stats = router.stats
    forwarded = ", ".join(f"{k} {v}" for k, v in sorted(stats.forwarded.items())) or "none"
    dropped = ", ".join(f"{k} {v}{why(k)}" for k, v in sorted(stats.dropped.items())) or "none"
    click.echo(f"forwarded {forwarded}; dropped {dropped}", err=True)


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


def _sim_key(value: str | None, passphrase_env: str | None) -> bytes:
    """``--key``: 64 hex digits, or a key file as ``--key-file`` reads it; or a passphrase."""
    from antireplay.mavlink import passphrase_key  # noqa: PLC0415

    if (value is None) == (passphrase_env is None):
        raise click.UsageError("give --key or --passphrase-env (one of them)")
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
    help="The vehicle's signing key: 64 hex digits, or a key file (32 raw bytes or 64 hex).",
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
def mavlink_sim(  # noqa: PLR0917 - one option per knob
    udp: str, pty: bool, key: str | None, passphrase_env: str | None, system_id: int, rate: float
) -> None:
    """A simulated signing vehicle: MAVLink 2 telemetry, and a COMMAND_ACK for each
    COMMAND_LONG that verifies; prints its counts when stopped (SIGTERM or Ctrl-C)."""
    from antireplay.mavlink.sim import SimVehicle  # noqa: PLC0415

    secret = _sim_key(key, passphrase_env)
    host, _, port = udp.rpartition(":")
    if not host or not (port.isascii() and port.isdigit()) or not 0 < int(port) < 65536:
        raise click.BadParameter(f"{udp!r}: expected HOST:PORT", param_hint="'--udp'")
    try:
        sim = SimVehicle(secret, system_id=system_id, udp=(host, int(port)), pty=pty, rate_hz=rate)
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


@click.group("mavlink-keys")
def mavlink_keys() -> None:
    """MAVProxy's signing.keys file (ENDPOINT PASSPHRASE per line), which --signing-keys reads."""


@mavlink_keys.command("add")
@click.argument("endpoint")
@click.option(
    "--file",
    "path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("~/.mavproxy/signing.keys"),
    show_default=True,
    help="The signing.keys file (created, mode 0600, if missing).",
)
@click.option(
    "--passphrase-env",
    default="MAV_PASSPHRASE",
    show_default=True,
    metavar="VAR",
    help="The environment variable holding the passphrase (never on the command line).",
)
def mavlink_keys_add(endpoint: str, path: Path, passphrase_env: str) -> None:
    """Give ENDPOINT the passphrase: adds its line once (running it again changes nothing;
    a different passphrase replaces the endpoint's line)."""
    phrase = os.environ.get(passphrase_env)
    if not phrase:
        _fail(f"--passphrase-env {passphrase_env}: not set")
    if len(phrase.split()) != 1 or phrase != phrase.strip() or len(endpoint.split()) != 1:
        _fail("the endpoint and the passphrase must be one word each (MAVProxy skips other lines)")
    path = path.expanduser()
    try:
        lines = path.read_text().splitlines() if path.exists() else []
    except (OSError, UnicodeDecodeError) as exc:
        _fail(f"--file {path}: unreadable ({exc})")
    entry = f"{endpoint} {phrase}"
    mine = [i for i, line in enumerate(lines) if line.split()[:1] == [endpoint]]
    if [lines[i] for i in mine] == [entry]:
        click.echo(f"{path}: {endpoint} already has this passphrase")
        return
    kept = [line for i, line in enumerate(lines) if i not in mine]
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as handle:
        handle.write("\n".join([*kept, entry]) + "\n")
    click.echo(f"{path}: {endpoint} {'replaced' if mine else 'added'}")
