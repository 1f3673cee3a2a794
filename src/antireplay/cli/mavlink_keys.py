"""``mavlink-keys``: the ``signing.keys`` file (``add``) and a vehicle's key (``provision``).

``provision`` parses its flags and calls :func:`~antireplay.wiring.mavlink_keys.provision`,
which refuses a link that is not wired (exit 2, naming it), refuses an armed vehicle and
enables the key (writes its ``sysid:N`` record) only once the vehicle signs with it (exit
1 otherwise, nothing written).  :func:`reload_on_sighup` is the router's SIGHUP hook.
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


def reload_on_sighup(router: MavlinkRouter, section: MavlinkConfig) -> None:
    """SIGHUP reads ``signing.keys`` again (one log line each time; a bad file keeps the
    old keys)."""
    from antireplay.wiring.mavlink_keys import reload_signing_keys  # noqa: PLC0415

    def handler(_signum: int, _frame: FrameType | None) -> None:
        log = logging.getLogger("antireplay.mavlink")
        try:
            log.warning(reload_signing_keys(router, section))
        except Exception as exc:  # a reload never stops the router
            log.warning("signing keys not reloaded, the old ones stay: %s", exc)

    signal.signal(signal.SIGHUP, handler)


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
    help="The new key's passphrase is in this environment variable (default: a random one, "
    "kept only in the file).",
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
    from antireplay.wiring.mavlink_keys import new_passphrase, provision  # noqa: PLC0415

    if passphrase_env is not None:
        phrase = os.environ.get(passphrase_env)
        if not phrase or len(phrase.split()) != 1 or phrase != phrase.strip():
            _fail(f"--passphrase-env {passphrase_env}: not set, or not one word")
    else:
        phrase = new_passphrase()
    path = path.expanduser()
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
        _fail(str(exc.strerror or exc))
    if not done.enabled:
        _fail(f"{link}: {done.reason}", code=1)
    said = "rotated" if done.rotated else "enabled"
    click.echo(f"{path}: system {system_id} key {said} ({done.reason})")
