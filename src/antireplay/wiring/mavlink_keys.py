"""``signing.keys`` records, key provisioning over a wired link, and the router's reload.

Theory of operation
-------------------
The file is MAVProxy's: lines ``ENDPOINT PASSPHRASE`` (the key is SHA-256 of the
passphrase).  A provisioned vehicle is one more such line, ``sysid:N PASSPHRASE``
(:func:`vehicle_record`): MAVProxy and older routers skip it (no device is named so), a
router whose ``--system-id`` is N takes it as its default key.  :func:`write_records`
replaces records and keeps every other line, written atomically (a temporary file of mode
0600 beside the file a symlink points to, fsynced, renamed; owner and group kept); ``add``
uses it too.

:func:`provision` drives :class:`~antireplay.mavlink.provision.Provisioning` on one link:
refused before anything is opened unless the link is wired; the new passphrase is written
first as a pending record (``sysid:N:pending``: the file proven writable, and the key kept if
anything fails once SETUP_SIGNING is out); SETUP_SIGNING is signed with the key the deciding
HEARTBEAT was signed with, sent only to that HEARTBEAT's source (the only one heard after);
the record replaces the pending one only once a fresh HEARTBEAT signed with the new key
verifies.  A port or device another process holds is refused (stop the router first).
:func:`reload_signing_keys` is the router's SIGHUP: it reads the file again
and gives each ground link the key the file now names (a new key gets its guard and its
timestamp source; a link whose line is gone falls back to the start-time default, or to one
key nobody holds; unused guards are dropped); a file that cannot be read keeps every key.
"""

from __future__ import annotations

import contextlib
import errno
import os
import queue
import secrets
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from antireplay.core.errors import ConfigError
from antireplay.mavlink.provision import vehicle_record
from antireplay.wiring.mavlink import _fingerprint, default_key, link_key, read_signing_keys

if TYPE_CHECKING:
    from collections.abc import Callable

    from antireplay.config import MavlinkConfig
    from antireplay.mavlink import Frame, MavlinkGuard, MavlinkRouter
    from antireplay.mavlink.endpoints import Peer, Transport
    from antireplay.mavlink.provision import Provisioning, Step

_RADIO_STATUS = 109  # a radio's own frames: heard from any source (the link is not wired)


def new_passphrase() -> str:
    """A random passphrase (one word, 256 bits): the key is its SHA-256, as MAVProxy's."""
    return secrets.token_urlsafe(32)


def pending_record(system_id: int) -> str:
    """The record of a key sent but not yet confirmed (``sysid:N:pending PASSPHRASE``): the
    vehicle may already use it, so it is written before SETUP_SIGNING goes out."""
    return f"{vehicle_record(system_id)}:pending"


def write_records(path: Path, changes: dict[str, str | None]) -> list[str]:
    """Give each record in ``changes`` its passphrase (None: drop it), every other line kept
    (names matched as the reader matches them: case aside).  Atomic (a temporary file in
    the directory of the file a symlink points to, fsynced, renamed), mode 0600, owner and
    group kept.  Returns warnings for the operator; OSError names the file."""
    target = Path(os.path.realpath(path))
    try:
        before = target.stat() if target.exists() else None
        lines = target.read_text().splitlines() if before is not None else []
    except UnicodeDecodeError:
        raise OSError(errno.EINVAL, "not a text file", str(path)) from None
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    names = {name.lower() for name in changes}
    kept = [line for line in lines if (line.split()[:1] or [""])[0].lower() not in names]
    added = [f"{name} {phrase}" for name, phrase in changes.items() if phrase is not None]
    warnings = []
    if before is not None and before.st_mode & 0o077:
        warnings.append(f"{path}: was mode {before.st_mode & 0o777:04o}, now 0600")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, temporary = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.")
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    try:
        with os.fdopen(fd, "w") as handle:
            if before is not None:
                with contextlib.suppress(PermissionError):  # not root: it stays ours
                    os.fchown(handle.fileno(), before.st_uid, before.st_gid)
            handle.write("".join(f"{line}\n" for line in [*kept, *added]))
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, target)
        directory = os.open(target.parent, os.O_RDONLY)
        try:
            os.fsync(directory)
        finally:
            os.close(directory)
    except BaseException as exc:
        Path(temporary).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise OSError(exc.errno, exc.strerror, str(path)) from None
        raise
    return warnings


def write_record(path: Path, name: str, passphrase: str) -> list[str]:
    """Give record ``name`` the passphrase (:func:`write_records`)."""
    return write_records(path, {name: passphrase})


def pending_passphrase(path: Path, system_id: int) -> str | None:
    """The passphrase of vehicle ``system_id``'s pending record, if ``path`` has one."""
    return read_signing_keys(path if path.exists() else None).get(pending_record(system_id))


@dataclass(frozen=True)
class Provisioned:
    """How an attempt ended: ``enabled`` (the record written) or why not; ``sent``: a
    SETUP_SIGNING went out, so the pending record stays (the vehicle may use that key)."""

    enabled: bool
    reason: str
    rotated: bool = False  # the vehicle had a key in the file, now replaced
    sent: bool = False
    warnings: tuple[str, ...] = ()


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
    ValueError for a bad connection string; OSError naming the file or the link that
    cannot be written or opened (nothing sent).  Once a SETUP_SIGNING is out, every
    failure (Ctrl-C included) is an answer with ``sent``: the pending record stays."""
    from antireplay.mavlink import open_transport, parse_endpoint, passphrase_key  # noqa: PLC0415
    from antireplay.mavlink.provision import Provisioning, wired  # noqa: PLC0415

    spec = parse_endpoint(link)
    if not wired(spec.kind, spec.host):
        raise ConfigError(
            "link", link, "a wired link", message=f"{link}: not a wired link (SETUP_SIGNING "
            "goes only over a serial/USB device or a loopback address)",
        )  # fmt: skip
    record, pending = vehicle_record(system_id), pending_record(system_id)
    current = read_signing_keys(path if path.exists() else None).get(record)
    old_key = passphrase_key(current) if current else None
    new_key = passphrase_key(passphrase)
    created = not path.exists()
    warnings = write_records(path, {pending: passphrase})  # writable, and kept, before a send

    def unsent() -> None:  # nothing went out: the pending record goes (and a file it made)
        if created:
            Path(os.path.realpath(path)).unlink(missing_ok=True)
        else:
            write_records(path, {pending: None})

    try:
        transport = open_transport(spec)
    except OSError as exc:
        unsent()
        busy = exc.errno in (errno.EADDRINUSE, errno.EBUSY)
        hint = " (stop the router using it first)" if busy else ""
        raise OSError(exc.errno, f"{exc.strerror or exc}{hint}", link) from exc
    attempt = Provisioning(new_key, system_id, time.time(), current=old_key, timeout_s=timeout_s)
    try:
        step = _drive(transport, attempt, new_key, on_sent)
    except (Exception, KeyboardInterrupt) as exc:
        if not attempt.sent:
            unsent()
            raise
        said = "interrupted" if isinstance(exc, KeyboardInterrupt) else f"failed ({exc})"
        return Provisioned(False, said, sent=True)
    finally:
        transport.close()
    if not step.enabled:
        if not attempt.sent:
            unsent()
        return Provisioned(False, step.reason, sent=attempt.sent, warnings=tuple(warnings))
    try:
        write_records(path, {record: passphrase, pending: None})
    except OSError as exc:
        return Provisioned(False, f"{exc}", sent=True, warnings=tuple(warnings))
    return Provisioned(True, step.reason, rotated=current is not None, warnings=tuple(warnings))


@dataclass(frozen=True)
class _Ended:
    enabled: bool
    reason: str


def _drive(
    transport: Transport, attempt: Provisioning, new_key: bytes,
    on_sent: Callable[[Step], object] | None,
) -> _Ended:  # fmt: skip
    """Run ``attempt`` on ``transport`` until it enables or refuses.  The source whose
    HEARTBEAT set the target is pinned: from then on only its frames are heard (and it
    alone is sent to); any other source still aborts with RADIO_STATUS or an armed
    HEARTBEAT, never steers."""
    from antireplay.mavlink.provision import StepKind, heartbeat_state  # noqa: PLC0415

    def alarming(frame: Frame) -> bool:
        state = heartbeat_state(frame)
        return frame.msgid == _RADIO_STATUS or (state is not None and state[1])

    heard: queue.Queue[tuple[Peer | None, list[Frame]]] = queue.Queue()
    transport.start(lambda _t, peer, frames, _skipped: heard.put((peer, frames)))
    pinned: list[Peer | None] = []
    while True:
        try:
            came_from, frames = heard.get(timeout=0.1)
        except queue.Empty:
            steps = [attempt.tick(time.time())]
        else:
            if pinned and came_from != pinned[0]:
                frames = [frame for frame in frames if alarming(frame)]
            steps = []
            for frame in frames:
                steps.append(attempt.heard(frame, time.time()))
                if not pinned and attempt.target is not None:
                    pinned.append(came_from)
        for step in steps:
            if step.kind is StepKind.SEND:
                setup = _setup_signing(step.target, new_key, step.timestamp, step.sign_with)
                transport.send(setup, pinned[0])
                if on_sent is not None:
                    on_sent(step)
            elif step.kind is StepKind.REFUSE:
                return _Ended(False, step.reason)
            elif step.kind is StepKind.ENABLE:
                return _Ended(True, step.reason)


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


def skipped_lines(path: str | Path) -> list[str]:
    """Lines of ``signing.keys`` that MAVProxy and the router skip (not ``ENDPOINT
    PASSPHRASE``), named for the operator; none if it cannot be read (its reader says so)."""
    try:
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        return []
    return [
        f"{path} line {number}: not ENDPOINT PASSPHRASE, skipped"
        for number, line in enumerate(lines, 1)
        if line.strip() and not line.lstrip().startswith("#") and len(line.split()) != 2
    ]


def key_file_notes(section: MavlinkConfig) -> list[str]:
    """What an operator should hear once about ``signing.keys``: :func:`skipped_lines`, and
    a ``sysid:N`` record that overrides ``--key-file`` or ``--passphrase-env`` as the
    default key."""
    path = section.signing_keys
    if path is None:
        return []
    notes = skipped_lines(path)
    record = vehicle_record(section.system_id)
    try:
        recorded = record in read_signing_keys(path)
    except ConfigError:  # gone since the router read it: the next reload says so
        recorded = False
    if recorded:
        given = [flag for flag, value in (("--key-file", section.key_file),
                 ("--passphrase-env", section.passphrase_env)) if value]  # fmt: skip
        if given:
            notes.append(f"default key: the {record} record of {path}, not {' or '.join(given)}")
    return notes


def reload_signing_keys(
    router: MavlinkRouter, section: MavlinkConfig, default: bytes | None, nobody: bytes
) -> str:
    """The router's SIGHUP (module docstring): one line saying what changed, or why
    nothing did.  ``default`` is the start-time default key, kept for every link without a
    line (the vehicle link keeps its key until a restart, so ground and vehicle never part
    on a changed ``sysid:N`` record: the line says to restart); ``nobody`` is the one key
    nobody holds, for a link left with no key (one guard, however many reloads).  Guards no
    link uses any more are stopped and dropped."""
    from antireplay.mavlink import Role, TimestampSource  # noqa: PLC0415

    try:
        keys = read_signing_keys(section.signing_keys)
        now_default = default_key(section, keys)
    except ConfigError as exc:
        return f"signing keys not reloaded, the old ones stay: {exc}"
    changed = []
    for link in router.links:
        if link.role is not Role.GROUND:
            continue
        try:
            key = link_key(link.name, keys, default)
        except ConfigError:  # its line is gone and no default: a key nobody holds
            key = nobody
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
    _drop_unused(router)
    links = ", ".join(changed) or "no link"
    said = f"signing keys reloaded from {section.signing_keys}: {links} changed"
    if now_default != default:
        said += (
            f"; the vehicle's key changed in {section.signing_keys}: restart the router to "
            "use it (until then every link keeps the key it started with)"
        )
    return said


def _drop_unused(router: MavlinkRouter) -> None:
    """Stop (flush, release the lease) and drop every guard and signer no link uses."""
    used = {router.vehicle_key} | {link.key for link in router.links if link.key is not None}
    unused = [guard for key, guard in router.inbound.items() if key not in used]
    router.inbound = {k: g for k, g in router.inbound.items() if k in used}
    router.signers = {k: s for k, s in router.signers.items() if k in used}
    for guard in unused:
        with contextlib.suppress(Exception):  # a store that fails: its lease expires alone
            guard.stop()


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
