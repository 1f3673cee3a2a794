"""What every command shares: one error idiom, the config and audit preflight, one shutdown.

An ordinary mistake is one line on stderr, ``antireplay: error: <what> (<what is
allowed>)``, with exit status 2 (:func:`_fail`); ``config check`` runs the same
:func:`preflight` as ``serve``, so a configuration that passes the check starts.

One shutdown for every long-running command: SIGINT (Ctrl-C) and SIGTERM end it with a
one-line summary and exit status 0.  A command with a loop of its own waits on the event
of :func:`stop_on_signal` and prints its counts; one that blocks elsewhere (a server, a
wait for readers, a scripted run) runs inside :func:`until_stopped`, which ends the
block at the signal, prints the summary it is given and exits 0.  A secret read from a
file that group or others may read gets one warning line (:func:`warn_if_shared`).
"""

from __future__ import annotations

import os
import signal
import sqlite3
import stat
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any, NoReturn

import click
from rich.console import Console

from antireplay.audit import verify
from antireplay.config import AppConfig
from antireplay.core.errors import AntiReplayError, ConfigError, StateFileError

console = Console()


class _Cli(click.Group):
    """click's usage errors as one unwrapped line on stderr (status 2), like ours."""

    def main(self, *args: Any, **kwargs: Any) -> Any:
        kwargs["standalone_mode"] = False
        try:
            code = super().main(*args, **kwargs)
        except click.exceptions.NoArgsIsHelpError as exc:
            exc.show()  # a bare group prints its help, as click does
            sys.exit(exc.exit_code)
        except click.ClickException as exc:
            _fail(exc.format_message(), exc.exit_code)
        except click.Abort:
            _fail("aborted", 1)
        except (OSError, AntiReplayError) as exc:  # a file or port the command could not use
            _fail(str(exc))
        sys.exit(code if isinstance(code, int) else 0)


def _fail(message: str, code: int = 2) -> NoReturn:
    """One line on stderr, never wrapped (newlines in a message are flattened)."""
    click.echo("antireplay: error: " + " ".join(message.split()), err=True)
    sys.exit(code)


def _load_config(path: Path | None, state_dir: Path) -> AppConfig:
    from antireplay.wiring import embedded_default  # noqa: PLC0415 - keeps `--help` fast

    try:
        return AppConfig.from_yaml(path) if path is not None else embedded_default(state_dir)
    except ConfigError as exc:
        _fail(str(exc))
    except OSError as exc:
        _fail(f"state directory {state_dir}: {exc.strerror or exc}")


def load_with_flags(path: Path | None, flags: dict[str, tuple[str, Any]]) -> AppConfig:
    """The configuration at ``path`` (none: the defaults) with a command's flags over its
    keys: ``flags`` maps a dotted key to ``(flag, value)``, ``None`` or ``()`` when the
    flag was not given.  A mistake is one line naming the flag when a flag made it."""
    try:
        return AppConfig.load(path, {key: value for key, (_, value) in flags.items()})
    except ConfigError as exc:
        flag, given = flags.get(exc.key, ("", None))
        _fail(f"{flag}: {exc}" if given not in (None, ()) else str(exc))


def _audit_problem(path: Path) -> str | None:
    """Why ``path`` is not an antireplay audit trail (read only: nothing is created)."""
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        return f"cannot open it ({exc})"
    try:
        columns = {row[1] for row in db.execute("PRAGMA table_info(audit)")}
    except sqlite3.DatabaseError as exc:
        return f"not an SQLite database ({exc})"
    finally:
        db.close()
    if not columns:
        return "an SQLite database without an audit table"
    missing = {"seq", "at", "outcome", "prev_hash", "hash"} - columns
    return f"its audit table lacks {', '.join(sorted(missing))}" if missing else None


def _check_audit_file(path: Path, remedy: str) -> None:
    problem = _audit_problem(path) if path.exists() else None
    if problem is not None:
        _fail(f"{path} is not an antireplay audit trail: {problem}; {remedy}")


_OPEN_ONLY_AUDIT = "audit verify and audit tail read only audit trails that antireplay wrote"
_MOVE_ASIDE = "move it aside (a new trail is started) or configure another path"


def _can_make_directory_in(parent: Path) -> bool:
    """Whether a directory can be made in ``parent`` (root passes ``os.access`` even on
    /proc): tried with a temporary one, removed at once, so nothing is left behind."""
    try:
        os.rmdir(tempfile.mkdtemp(dir=parent, prefix=".antireplay-check-"))
    except OSError:
        return False
    return True


def _check_audit_anchor(path: Path) -> None:
    """What opening the trail would refuse, found read-only (nothing written, nothing adopted)."""
    existing = next(p for p in (path.absolute().parent, *path.absolute().parents) if p.exists())
    if (
        not existing.is_dir()
        or not os.access(existing, os.W_OK | os.X_OK)
        or (existing != path.absolute().parent and not _can_make_directory_in(existing))
    ):
        _fail(f"audit {path}: cannot create its directory ({existing} is not a writable directory)")
    if not path.exists():
        return
    try:
        report = verify(path)
    except StateFileError as exc:
        _fail(str(exc))
    if report.records and report.head != "match":
        _fail(
            f"audit {path}: head checkpoint {report.head}; see `antireplay audit verify {path}`, "
            f"then `antireplay audit reanchor {path}` or move the trail aside"
        )


def importable_cwd(upstream: str | None) -> None:
    """Put the working directory on ``sys.path`` (as ``python -m`` does), so a
    ``module:function`` upstream in it imports without ``PYTHONPATH=.``; appended, so a
    file there never shadows an installed package.  Only for such an upstream: otherwise
    nothing is imported from the working directory at all."""
    if upstream is None or upstream.startswith(("http://", "https://")):
        return
    cwd = str(Path.cwd())
    if cwd not in sys.path and "" not in sys.path:
        sys.path.append(cwd)


def preflight(config: AppConfig) -> None:
    """Every check ``serve`` makes before it listens; exits with one line on the first failure."""
    from antireplay.wiring.gateway import check_gateway  # noqa: PLC0415
    from antireplay.wiring.leaves import check_state  # noqa: PLC0415

    importable_cwd(config.upstream)
    try:
        check_gateway(config)
    except ConfigError as exc:
        _fail(str(exc))
    _check_audit_file(Path(config.audit), f"audit: {_MOVE_ASIDE}")
    _check_audit_anchor(Path(config.audit))
    try:
        check_state(config.store_spec)
    except (ConfigError, StateFileError) as exc:  # each names its input and the recovery
        _fail(str(exc))
    except Exception as exc:  # any backend's own failure, named with its spec
        _fail(f"store {config.store}: cannot open it ({type(exc).__name__}: {exc})")


def stop_on_signal() -> threading.Event:
    """An event set by SIGINT or SIGTERM: a long-running command waits on it, then stops."""
    stop = threading.Event()

    def handler(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
    return stop


class _Stopped(BaseException):
    """Raised in the main thread by the first SIGINT or SIGTERM inside :func:`until_stopped`
    (a ``BaseException``: no ``except Exception`` on the way swallows it)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


@contextmanager
def until_stopped(summary: Callable[[], str]) -> Iterator[None]:
    """Run the block until SIGINT or SIGTERM; then print ``summary()`` as one line on stderr
    (``stopped by SIGINT: ...``) and exit 0.  Later signals are ignored while it stops."""
    stopping: list[int] = []

    def handler(signum: int, _frame: FrameType | None) -> None:
        if not stopping:
            stopping.append(signum)
            raise _Stopped(signum)

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    except _Stopped as stop:
        name = signal.Signals(stop.signum).name
        click.echo(f"stopped by {name}: {summary()}", err=True)
        sys.exit(0)
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


#: What the drop codes of the MAVLink router and the PQ ends mean, for their exit counts
#: (a refusal's code is in docs/codes.md); looked up by ``side:CODE``, then by ``CODE``.
_DROPS = {
    "air:NO_PEER": "no peer on the air side yet: none authenticated to this end",
    "NO_PEER": "accepted, but no other link had a receiver yet: telemetry before a ground "
    "station authenticated",
    "NO_ROUTE": "targeted at a system never seen",
    "SOURCE_BOUND": "claimed the ids a ground station authenticated on another link",
    "UNREACHABLE": "the link could not take the frame: disconnected or full",
}


def why(key: str) -> str:
    """`` (what it means)`` for a counted drop ``side:CODE`` that needs saying, else ``""``."""
    meaning = _DROPS.get(key) or _DROPS.get(key.rpartition(":")[2])
    return f" ({meaning})" if meaning else ""


def warn_if_shared(path: Path, what: str) -> None:
    """One warning line if the secret ``path`` may be read by group or others."""
    try:
        mode = path.stat().st_mode
    except OSError:
        return  # the reader names what is wrong with it
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        click.echo(
            f"antireplay: warning: {what} {path} is open to group or others (mode "
            f"{stat.S_IMODE(mode):04o}); keep a secret mode 0600: chmod 600 {path}",
            err=True,
        )
