"""The MAVLink router, wired: the ``mavlink:`` section in, a running router's parts out.

Theory of operation
-------------------
:func:`open_router` is all ``mavlink-router`` does between reading its configuration and
waiting for a signal, leaves first: the link keys (:func:`router_endpoints`: a key file,
a passphrase from the environment, MAVProxy's ``signing.keys``, whose ``sysid:N`` record,
N the router's system id, is the default key: :func:`default_key`), the allow-lists
(:func:`allowed_messages`), the audit trail with its retention, spill and floors, and the
store (its spec parsed once, anchored as ``state.anchor`` says) through
:mod:`~antireplay.wiring.leaves`, the same functions ``serve`` opens its own through.
:func:`build_mavlink_router` builds the router on an opened store and audit trail: its
endpoints, an inbound guard per key (bound to ``system_id``), the outbound guard, each on
its own store prefix (``mav-in``, ``mav-out``), a durable timestamp source per key the
router signs with, and the refusal handler (:func:`mavlink_auditor`), which logs why each
dropped frame was refused and records it with its direction and the source its header
claims (``mav:inbound:255/190``, unverified) through the one rate-limited
:class:`~antireplay.audit.RefusalAuditor`; what it folds is a metric.  A trusted endpoint
(signed on its behalf) must be loopback or serial unless ``trust_network`` acknowledges it
(:func:`trusted_endpoints`); :func:`fence_notice` says a restart fence on the start line and
in readiness.  The MAVLink stack
is imported only when a router is built, so the gateway does not load the MAVLink dialect.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from antireplay.audit import AuditLog
from antireplay.audit.space import DiskSpace
from antireplay.config import AppConfig, MavlinkConfig
from antireplay.core.errors import ConfigError
from antireplay.state import ReplayStore, StoreSpec
from antireplay.wiring.leaves import open_state, open_trail, trail_path
from antireplay.wiring.refusals import MavlinkRefusals, mavlink_auditor

if TYPE_CHECKING:
    from antireplay.mavlink import MavlinkRouter, Role

#: The router's trail unless ``audit.path`` (or ``--audit``) names one.
ROUTER_AUDIT = ".antireplay/mavlink-audit.db"


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
    #: Trusted endpoints acknowledged on the network (:func:`trusted_endpoints`).
    trust_network: frozenset[str] = frozenset()


def build_mavlink_router(
    endpoints: Sequence[tuple[Role, str, bytes | None]],
    store: ReplayStore,
    audit: AuditLog,
    options: RouterOptions = RouterOptions(),
    on_reject: MavlinkRefusals | None = None,
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
    from antireplay.mavlink import (  # noqa: PLC0415 - the dialect loads on use
        MavlinkGuard,
        MavlinkRouter,
        Role,
        RouterLink,
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
    links: list[RouterLink] = []
    try:
        for role, spec, key in specs:
            try:
                network = role is Role.TRUSTED and spec.text in options.trust_network
                links.append(RouterLink(open_transport(spec), role, key, network=network))
            except OSError as exc:
                raise OSError(exc.errno, f"{spec.text}: {exc.strerror or exc}") from exc
    except BaseException:
        for link in links:
            link.transport.close()
        raise
    return MavlinkRouter(
        links, inbound, outbound, signers=signers, sign_link_id=options.sign_link_id,
        on_reject=on_reject or mavlink_auditor(audit),
    )  # fmt: skip


_FENCE_WHY = {
    "lease": (
        "the previous run did not release its lease (a crash?): frames it accepted up to "
        "then may come back", "it passes by itself; a clean stop (SIGTERM) releases the "
        "lease at the stop time",
    ),
    "high": (
        "the previous run accepted a frame stamped {ahead:.1f} s ahead of this clock (its "
        "highest timestamp, by whole seconds)", "it passes when the wall clock reaches that "
        "timestamp",
    ),
}  # fmt: skip


def fence_notice(router: MavlinkRouter, store: ReplayStore, wall: float) -> str | None:
    """``fenced until T (n s more): why; what removes it`` while the router's restart
    fence lies ahead of ``wall`` (every frame stamped now is refused), else ``None``."""
    from antireplay.mavlink.fencing import until_text  # noqa: PLC0415

    fence = router.fence()
    if fence is None:
        return None
    why, remedy = _FENCE_WHY.get(fence[1]) or _lost_why(store)
    if fence[1] == "high":  # how far ahead, said (the store's loss reason is never formatted)
        why = why.format(ahead=max(0.0, fence[0] - wall))
    return f"fenced{until_text(fence, wall)}: {why}; {remedy}"


def _lost_why(store: ReplayStore) -> tuple[str, str]:
    """Why a state fences as new or lost, and what removes it: the store's own reason for
    a loss it found at this open; a memory store's missing history; else a persistent
    state still inside the first fence it took when it began (a restart does not end it)."""
    reason = getattr(store, "loss_reason", None)
    passes = "it passes by itself"
    if store.backend == "memory":
        return (
            reason or "a memory store starts with no history of what an earlier run accepted",
            f"{passes}; a persistent store kept across restarts (--store sqlite:PATH, "
            "mavlink.store) starts unfenced after a clean stop, and a state anchor "
            "(state.anchor) proves a restored one",
        )
    return (
        reason
        or f"this {store.backend} state is new: fenced since its first start, as "
        "it cannot know what a run before it accepted",
        f"{passes} (a restart does not shorten it); a state anchor (state.anchor) proves "
        "a restored one",
    )


def stop_router(router: MavlinkRouter) -> None:
    """Stop the router, then write its folded refusals' summary rows (before its audit
    trail closes)."""
    router.stop()
    if isinstance(router.on_reject, MavlinkRefusals):
        router.on_reject.close()


def _fingerprint(key: bytes) -> str:
    """A short public name for a key (store prefixes): not the key, not reversible."""
    return hashlib.sha256(b"antireplay mavlink key" + key).hexdigest()[:12]


def read_key_file(path: str, key: str = "mavlink.key_file") -> bytes:
    """A link key: exactly 32 raw bytes (taken as they are: a raw key may begin or end with
    a whitespace byte), or 64 hex characters with optional surrounding whitespace."""
    try:
        raw = Path(path).read_bytes()
    except FileNotFoundError:
        raise ConfigError.file_not_found(key, path) from None
    except OSError as exc:
        raise ConfigError(key, path, f"a readable key file ({exc.strerror})") from None
    if len(raw) == 32:
        return raw
    text = raw.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except ValueError:
            pass
    raise ConfigError(
        key, path, "a MAVLink signing key", message=f"{key} {path}: not a MAVLink signing key "
        "(32 raw bytes or 64 hex digits)",
    )  # fmt: skip


def read_signing_keys(path: str | Path | None) -> dict[str, str]:
    """MAVProxy's ``signing.keys``: lines ``ENDPOINT PASSPHRASE`` (endpoint as typed)."""
    if path is None:
        return {}
    try:
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError("mavlink.signing_keys", path, f"a readable file ({exc})") from None
    found = {}
    for line in lines:
        words = line.split()
        if len(words) == 2:
            found[words[0].lower()] = words[1]
    return found


def passphrase_from(variable: str, key: str) -> bytes:
    """The key derived from the passphrase in environment ``variable`` (as MAVProxy does)."""
    from antireplay.mavlink import passphrase_key  # noqa: PLC0415 - the dialect loads on use

    phrase = os.environ.get(variable)
    if not phrase:
        said = f"{key} {variable}: is not set (the passphrase's environment variable)"
        raise ConfigError(key, variable, "a set environment variable", message=said)
    return passphrase_key(phrase)


def link_key(endpoint: str, keys: dict[str, str], default: bytes | None) -> bytes:
    """A link's key: its passphrase in the signing-keys file (matched as MAVProxy matches:
    the whole string, or ``HOST:PORT`` against ``PROTO:HOST:PORT``), else the default."""
    from antireplay.mavlink import passphrase_key  # noqa: PLC0415 - the dialect loads on use

    text = endpoint.lower()
    host_port = text.partition(":")[2] if text.count(":") == 2 else None
    passphrase = keys.get(text) or (keys.get(host_port) if host_port else None)
    if passphrase is not None:
        return passphrase_key(passphrase)
    if default is None:
        raise ConfigError(
            "mavlink.key_file", endpoint, "a key", message=f"{endpoint}: no key (give "
            "--key-file, --passphrase-env or a --signing-keys entry; mavlink.key_file, "
            "mavlink.passphrase_env or mavlink.signing_keys)",
        )  # fmt: skip
    return default


def allowed_messages(entries: Sequence[str]) -> tuple[Allowed, Allowed]:
    """``allow_unsigned`` entries ``[to-vehicle:|from-vehicle:]MESSAGE[:v1]``, per direction
    (to the vehicle, from it)."""
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
            raise ConfigError(
                "mavlink.allow_unsigned", entry, "[to-vehicle:|from-vehicle:]MESSAGE[:v1], "
                "MESSAGE a name (RADIO_STATUS) or an id (--allow-unsigned)",
            )  # fmt: skip
        for direction in directions:
            sets[direction][0].add(msgid)
            if v1:
                sets[direction][1].add(msgid)
    to_vehicle, from_vehicle = (
        Allowed(frozenset(unsigned), frozenset(v1)) for unsigned, v1 in sets.values()
    )
    return to_vehicle, from_vehicle


def default_key(section: MavlinkConfig, keys: dict[str, str]) -> bytes | None:
    """The key of every link without a line of its own: the vehicle's provisioned record
    (``sysid:N``, N the router's system id), else the key file or the passphrase."""
    from antireplay.mavlink import passphrase_key  # noqa: PLC0415 - the dialect loads on use
    from antireplay.mavlink.provision import vehicle_record  # noqa: PLC0415

    default = read_key_file(section.key_file) if section.key_file is not None else None
    if section.passphrase_env is not None:
        if default is not None:
            raise ConfigError(
                "mavlink.passphrase_env", section.passphrase_env, "one default key",
                message="give --key-file or --passphrase-env (mavlink.key_file or "
                "mavlink.passphrase_env), not both",
            )  # fmt: skip
        default = passphrase_from(section.passphrase_env, "mavlink.passphrase_env")
    provisioned = keys.get(vehicle_record(section.system_id))
    return default if provisioned is None else passphrase_key(provisioned)


def router_endpoints(section: MavlinkConfig) -> list[tuple[Role, str, bytes | None]]:
    """``(role, connection string, key)`` for every endpoint the section names."""
    from antireplay.mavlink import Role  # noqa: PLC0415 - the dialect loads on use

    if not section.vehicle:
        raise ConfigError(
            "mavlink.vehicle", [], "a vehicle endpoint", message="give at least one "
            "--vehicle (or --forward; mavlink.vehicle in the configuration)",
        )  # fmt: skip
    keys = read_signing_keys(section.signing_keys)
    default = default_key(section, keys)
    endpoints: list[tuple[Role, str, bytes | None]] = [
        (Role.VEHICLE, text, link_key(text, keys, default)) for text in section.vehicle
    ]
    endpoints += [(Role.GROUND, text, link_key(text, keys, default)) for text in section.ground]
    endpoints += [(Role.TRUSTED, text, None) for text in trusted_endpoints(section)]
    return endpoints


def trusted_endpoints(section: MavlinkConfig) -> list[str]:
    """``trusted``, each loopback or a serial device unless ``trust_network`` acknowledges
    it exactly: the router signs whatever a trusted endpoint sends with the vehicle key, so
    on the network anyone who reaches it commands the vehicle.  ConfigError names the
    endpoint (or an acknowledgement that names no trusted network endpoint)."""
    from antireplay.mavlink import is_local, parse_endpoint  # noqa: PLC0415
    from antireplay.mavlink.endpoints import addresses  # noqa: PLC0415

    local: dict[str, bool] = {}
    seen: dict[str, str] = {}
    for text in section.trusted:
        try:
            spec = parse_endpoint(text)
        except ValueError as exc:
            raise ConfigError("mavlink.trusted", text, "an endpoint", message=str(exc)) from None
        local[text] = is_local(spec)
        found = (spec.host,) if local[text] else addresses(spec)
        if not found:
            seen[text] = f" ({spec.host} does not resolve)"
        elif found != (spec.host.strip("[]"),):  # a name, or a literal in another form
            seen[text] = f" ({spec.host} resolves to {', '.join(found)})"
    for text in section.trust_network:
        if local.get(text, True):
            said = "is not a --trusted endpoint" if text not in local else "is local already"
            raise ConfigError(
                "mavlink.trust_network", text, "a trusted endpoint on the network, as given",
                message=f"--trust-network {text}: {said} (mavlink.trust_network names a "
                "--trusted endpoint that is not loopback or serial, exactly as given)",
            )  # fmt: skip
    for text, is_loopback in local.items():
        if not is_loopback and text not in section.trust_network:
            raise ConfigError(
                "mavlink.trusted", text, "a loopback or serial endpoint",
                message=f"--trusted {text}: not loopback or a serial device"
                f"{seen.get(text, '')}, and the router signs whatever it receives with the "
                "vehicle key (anyone who reaches it commands the vehicle); bind it to "
                "127.0.0.1, or acknowledge this exact "
                f"endpoint with --trust-network {text} (mavlink.trust_network)",
            )  # fmt: skip
    return list(section.trusted)


def router_options(section: MavlinkConfig) -> RouterOptions:
    """The guards' knobs the section sets."""
    to_vehicle, from_vehicle = allowed_messages(section.allow_unsigned)
    return RouterOptions(
        section.system_id, to_vehicle, from_vehicle, section.reorder_window,
        section.write_through, section.max_forward_s, section.new_stream_max_age_s,
        section.sign_link_id, frozenset(section.trust_network),
    )  # fmt: skip


@dataclass
class RouterParts:
    """What ``mavlink-router`` runs and closes: the router on its store and trail."""

    router: MavlinkRouter
    endpoints: list[tuple[Role, str, bytes | None]]
    store: ReplayStore
    store_spec: StoreSpec
    audit: AuditLog
    space: DiskSpace

    def close(self) -> None:
        """Stop the router, record the folded refusals, close the trail, then the store."""
        stop_router(self.router)
        self.audit.close()
        self.store.close()


def open_router(config: AppConfig, audit_path: str | None = None) -> RouterParts:
    """The router the ``mavlink:`` section describes, on its store and audit trail (at
    ``audit_path``; default :func:`trail_path`), opened as ``serve`` opens its own.

    Raises ConfigError (a key, a key file, an allow-list entry), StateFileError (the trail
    or the store), ValueError (an endpoint string), OSError (an endpoint that cannot be
    opened, named), ReplayAttackError (a store rolled back)."""
    section = config.mavlink
    endpoints = router_endpoints(section)
    options = router_options(section)
    spec = section.store_spec
    path = audit_path or trail_path(config, ROUTER_AUDIT)
    audit, space = open_trail(config, path)  # rotated, retained, with a spill and floors
    opened: list[AuditLog | ReplayStore] = [audit]
    try:
        store = open_state(config, spec, audit_path=path)
        opened.append(store)
        on_reject = mavlink_auditor(audit, quiet=space.low)
        router = build_mavlink_router(endpoints, store, audit, options, on_reject)
    except BaseException:
        for leaf in reversed(opened):  # what this call opened, closed again
            leaf.close()
        raise
    return RouterParts(router, endpoints, store, spec, audit, space)
