"""``signing.keys`` records, key provisioning over a wired link, and the router's reload.

Theory of operation
-------------------
The file is MAVProxy's: lines ``ENDPOINT PASSPHRASE`` (the key is SHA-256 of the
passphrase).  A provisioned vehicle is one more such line, ``sysid:N PASSPHRASE``
(:func:`vehicle_record`): MAVProxy and older routers skip it (no device is named so), a
router whose ``--system-id`` is N takes it as its default key.  :func:`write_record`
replaces one record and keeps every other line, written atomically (a temporary file of
mode 0600 in the same directory, fsynced, renamed over the old one).

:func:`provision` drives :class:`~antireplay.mavlink.provision.Provisioning` on one link:
refused before anything is opened unless the link is wired; SETUP_SIGNING signed with the
vehicle's current key when the file has one (a vehicle with signing on takes only that),
unsigned otherwise; the new record is written only after a HEARTBEAT signed with the new
key verifies.  :func:`reload_signing_keys` is the router's SIGHUP: it reads the file again
and gives each ground link the key the file now names (a new key gets its guard and its
timestamp source; a link whose line is gone falls back to the default key, or refuses
everything); a file that cannot be read keeps every key as it was.
"""

from __future__ import annotations

import os
import queue
import secrets
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from antireplay.core.errors import ConfigError
from antireplay.wiring.mavlink import _fingerprint, default_key, link_key, read_signing_keys

if TYPE_CHECKING:
    from collections.abc import Callable

    from antireplay.config import MavlinkConfig
    from antireplay.mavlink import Frame, MavlinkGuard, MavlinkRouter
    from antireplay.mavlink.endpoints import Peer
    from antireplay.mavlink.provision import Step


def new_passphrase() -> str:
    """A random passphrase (one word, 256 bits): the key is its SHA-256, as MAVProxy's."""
    return secrets.token_urlsafe(32)


def write_record(path: Path, name: str, passphrase: str) -> None:
    """Give record ``name`` the passphrase: its old line replaced, every other line kept;
    atomic, mode 0600."""
    lines = path.read_text().splitlines() if path.exists() else []
    kept = [line for line in lines if line.split()[:1] != [name]]
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")  # mode 0600
    try:
        with os.fdopen(fd, "w") as handle:
            handle.write("\n".join([*kept, f"{name} {passphrase}"]) + "\n")
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


@dataclass(frozen=True)
class Provisioned:
    """How an attempt ended: ``enabled`` (the record written) or why not."""

    enabled: bool
    reason: str
    rotated: bool = False  # the vehicle had a key in the file, now replaced


def provision(
    link: str,
    path: Path,
    passphrase: str,
    *,
    system_id: int = 1,
    timeout_s: float = 10.0,
    on_sent: Callable[[Step], object] | None = None,
) -> Provisioned:
    """Provision vehicle ``system_id`` on ``link`` with ``passphrase`` (module docstring).

    ConfigError when ``link`` is not wired or the file cannot be read (nothing sent);
    ValueError for a bad connection string; OSError naming a link that cannot be opened.
    ``on_sent`` hears each SETUP_SIGNING sent."""
    from antireplay.mavlink import open_transport, parse_endpoint, passphrase_key  # noqa: PLC0415
    from antireplay.mavlink.provision import (  # noqa: PLC0415
        Provisioning,
        StepKind,
        vehicle_record,
        wired,
    )

    spec = parse_endpoint(link)
    if not wired(spec.kind, spec.host):
        raise ConfigError(
            "link", link, "a wired link", message=f"{link}: not a wired link (SETUP_SIGNING "
            "goes only over a serial/USB device or a loopback address)",
        )  # fmt: skip
    record = vehicle_record(system_id)
    current = read_signing_keys(path if path.exists() else None).get(record)
    old_key = passphrase_key(current) if current else None
    new_key = passphrase_key(passphrase)
    try:
        transport = open_transport(spec)
    except OSError as exc:
        raise OSError(exc.errno, f"{link}: {exc.strerror or exc}") from exc
    heard: queue.Queue[tuple[Peer | None, list[Frame]]] = queue.Queue()
    transport.start(lambda _t, peer, frames, _skipped: heard.put((peer, frames)))
    attempt = Provisioning(new_key, system_id, time.time(), timeout_s=timeout_s)
    peer: Peer | None = None
    try:
        while True:
            try:
                came_from, frames = heard.get(timeout=0.1)
            except queue.Empty:
                steps = [attempt.tick(time.time())]
            else:
                steps = [attempt.heard(frame, time.time()) for frame in frames]
                if any(frame.sysid == system_id for frame in frames):
                    peer = came_from
            for step in steps:
                if step.kind is StepKind.SEND:
                    setup = _setup_signing(step.target, new_key, step.timestamp, old_key)
                    transport.send(setup, peer)
                    if on_sent is not None:
                        on_sent(step)
                elif step.kind is StepKind.REFUSE:
                    return Provisioned(False, step.reason)
                elif step.kind is StepKind.ENABLE:
                    write_record(path, record, passphrase)
                    return Provisioned(True, step.reason, rotated=current is not None)
    finally:
        transport.close()


def _setup_signing(
    target: tuple[int, int], key: bytes, timestamp: int, old_key: bytes | None
) -> bytes:
    """SETUP_SIGNING from a ground station (255/190), signed with ``old_key`` if given."""
    from pymavlink.dialects.v20 import ardupilotmega as dialect  # noqa: PLC0415

    mav = dialect.MAVLink(None, srcSystem=255, srcComponent=190)
    if old_key is not None:
        mav.signing.secret_key = old_key
        mav.signing.sign_outgoing = True
        mav.signing.timestamp = timestamp
    message = dialect.MAVLink_setup_signing_message(target[0], target[1], list(key), timestamp)
    return bytes(message.pack(mav))


def reload_signing_keys(router: MavlinkRouter, section: MavlinkConfig) -> str:
    """The router's SIGHUP (module docstring): one line saying what changed, or why
    nothing did.  The vehicle key is kept (it changes at a restart)."""
    from antireplay.mavlink import Role, TimestampSource  # noqa: PLC0415

    try:
        keys = read_signing_keys(section.signing_keys)
        default = default_key(section, keys)
    except ConfigError as exc:
        return f"signing keys not reloaded, the old ones stay: {exc}"
    changed = []
    for link in router.links:
        if link.role is not Role.GROUND:
            continue
        try:
            key = link_key(link.name, keys, default)
        except ConfigError:  # its line is gone and no default: a key nobody holds
            key = secrets.token_bytes(32)
        if key == link.key:
            continue
        if key not in router.inbound:
            template = router.inbound[router.vehicle_key]
            router.inbound = {**router.inbound, key: _sibling(template, key)}
            signer = TimestampSource(
                store=template.store,
                store_key=f"mav-sign-{_fingerprint(key)}-{router.sign_link_id}",
            )
            router.signers = {**router.signers, key: signer}
        link.key = key
        changed.append(link.name)
    links = ", ".join(changed) or "no link"
    return f"signing keys reloaded from {section.signing_keys}: {links} changed"


def _sibling(template: MavlinkGuard, key: bytes) -> MavlinkGuard:
    """A guard like ``template`` for another key, on that key's own store prefix."""
    from antireplay.mavlink import UNITS_PER_S, MavlinkGuard  # noqa: PLC0415

    return MavlinkGuard(
        key, store=template.store, clock=template.clock, system_id=template.system_id,
        allow_unsigned=template.allow_unsigned, allow_v1=template.allow_v1,
        reorder_window=template.reorder_window, write_through=template.write_through,
        store_prefix=f"mav-in-{_fingerprint(key)}",
        max_forward_s=template.max_forward / UNITS_PER_S,
        new_stream_max_age_s=template.new_stream_max_age / UNITS_PER_S,
        persist_interval_s=template.persist_interval_s,
    )  # fmt: skip
