"""``mavlink-keys``: the ``signing.keys`` file (``add``) and a vehicle's key (``provision``).

``provision`` parses its flags and calls :func:`~antireplay.wiring.mavlink_keys.provision`,
which refuses a link that is not wired or a file it cannot write (exit 2, naming it, nothing
sent), refuses an armed vehicle and enables the key (its ``sysid:N`` record) only once the
vehicle signs with it, freshly; otherwise exit 1, and if a SETUP_SIGNING went out the message
says where the pending key is kept (running the command again resumes with it).
:func:`reload_on_sighup` is the router's SIGHUP hook.
"""

from __future__ import annotations

import logging
import os
import signal
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING

import click

from antireplay.cli._common import _fail
from antireplay.core.errors import ConfigError

if TYPE_CHECKING:
    from antireplay.config import MavlinkConfig
    from antireplay.mavlink import MavlinkRouter

_DEFAULT_FILE = Path("~/.mavproxy/signing.keys")


def reload_on_sighup(router: MavlinkRouter, section: MavlinkConfig) -> str:
    """SIGHUP reads ``signing.keys`` again (one log line each time; a bad file keeps the
    old keys).  Installed before the router starts: a SIGHUP during start-up reloads.
    Returns what the start line adds about the file (skipped lines, the default key's
    source when a ``sysid:N`` record overrides a flag), once."""
    import secrets  # noqa: PLC0415

    from antireplay.wiring.mavlink import default_key, read_signing_keys  # noqa: PLC0415
    from antireplay.wiring.mavlink_keys import key_file_notes, reload_signing_keys  # noqa: PLC0415

    default = default_key(section, read_signing_keys(section.signing_keys))
    nobody = secrets.token_bytes(32)  # one key nobody holds, for every link left keyless

    def handler(_signum: int, _frame: FrameType | None) -> None:
        log = logging.getLogger("antireplay.mavlink")
        try:
            log.warning(reload_signing_keys(router, section, default, nobody))
        except Exception as exc:  # a reload never stops the router
            log.warning("signing keys not reloaded, the old ones stay: %s", exc)

    signal.signal(signal.SIGHUP, handler)
    return "".join(f"; {note}" for note in key_file_notes(section))


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
    from antireplay.wiring.mavlink import read_signing_keys  # noqa: PLC0415
    from antireplay.wiring.mavlink_keys import write_record  # noqa: PLC0415

    path = path.expanduser()
    try:
        had = read_signing_keys(path if path.exists() else None).get(endpoint.lower())
    except ConfigError as exc:
        _fail(f"--file {path}: not a readable signing.keys file ({exc})")
    if had == phrase:
        click.echo(f"{path}: {endpoint} already has this passphrase")
        return
    try:
        warnings = write_record(path, endpoint, phrase)
    except OSError as exc:
        _fail(f"--file {exc.filename or path}: not written ({exc.strerror or exc}); unchanged")
    for warning in warnings:
        click.echo(warning, err=True)
    click.echo(f"{path}: {endpoint} {'replaced' if had is not None else 'added'}")


@mavlink_keys.command("provision")
@click.argument("link")
@click.option(
    "--file",
    "path",
    type=click.Path(dir_okay=False, path_type=Path),
    default=_DEFAULT_FILE,
    show_default=True,
    help="The signing.keys file the vehicle's record (sysid:N) goes in (mode 0600).",
)
@click.option(
    "--system-id",
    type=click.IntRange(1, 255),
    default=1,
    show_default=True,
    help="The vehicle's system id.",
)
@click.option(
    "--passphrase-env",
    default=None,
    metavar="VAR",
    help="The new key's passphrase is in this environment variable (default: the file's "
    "pending key if it has one, else a random one, kept only in the file).",
)
@click.option(
    "--timeout",
    "timeout_s",
    type=click.FloatRange(0.5, 600),
    default=10.0,
    show_default=True,
    help="Give up (nothing enabled) if the vehicle does not sign with the new key by then.",
)
def mavlink_keys_provision(
    link: str, path: Path, system_id: int, passphrase_env: str | None, timeout_s: float
) -> None:
    """Send the vehicle a new signing key (SETUP_SIGNING) over LINK, a serial/USB device or a
    loopback address, and record it once the vehicle signs with it."""
    from antireplay.wiring.mavlink_keys import (  # noqa: PLC0415
        new_passphrase,
        pending_passphrase,
        pending_record,
        provision,
        skipped_lines,
    )

    path = path.expanduser()
    try:
        pending = pending_passphrase(path, system_id)
    except ConfigError:
        _fail(f"--file {path}: not a readable signing.keys file")
    given = os.environ.get(passphrase_env) if passphrase_env is not None else None
    if passphrase_env is not None and (
        not given or len(given.split()) != 1 or given != given.strip()
    ):
        _fail(f"--passphrase-env {passphrase_env}: not set, or not one word")
    if pending is not None and given is not None and given != pending:
        _fail(
            f"--file {path}: system {system_id} has a pending key ({pending_record(system_id)}) "
            "the vehicle may already use: finish it first (run again without --passphrase-env)"
        )
    phrase = given or pending or new_passphrase()
    for skipped in skipped_lines(path):
        click.echo(f"antireplay: warning: {skipped}", err=True)
    if pending is not None:
        click.echo(f"{path}: resuming system {system_id}'s pending key")
    try:
        done = provision(
            link, path, phrase, system_id=system_id, timeout_s=timeout_s,
            on_sent=lambda _step: click.echo(f"{link}: SETUP_SIGNING sent to system {system_id}"),
        )  # fmt: skip
    except ConfigError as exc:
        _fail(str(exc))
    except ValueError as exc:
        _fail(f"{link}: {exc}")
    except OSError as exc:
        where = exc.filename or link
        _fail(f"{where}: {exc.strerror or exc}; nothing sent")
    for warning in done.warnings:
        click.echo(warning, err=True)
    if not done.enabled and done.sent:
        _fail(
            f"{link}: {done.reason}; the vehicle may already use the new key: its passphrase "
            f"is kept in {path} as {pending_record(system_id)}; run the same command again "
            "(no --passphrase-env) to finish",
            code=1,
        )
    if not done.enabled:
        _fail(f"{link}: {done.reason} (nothing sent)", code=1)
    said = "rotated" if done.rotated else "enabled"
    click.echo(f"{path}: system {system_id} key {said} ({done.reason})")
