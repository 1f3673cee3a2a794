"""The ``antireplay`` command line (click + rich): a thin adapter over the library.

Errors are for people: an ordinary mistake (a bad option value, a missing or
foreign file, a busy port, a configuration ``serve`` would refuse) is one line
on stderr, ``antireplay: error: <what> (<what is allowed>)``, never wrapped,
with exit status 2, and never a traceback.  :class:`_Cli` gives click's own
usage errors that shape too.  ``config check`` runs the same :func:`preflight`
as ``serve``, so a configuration that passes the check starts.
"""

from __future__ import annotations

import importlib
import json
import os
import sqlite3
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import click
import httpx
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ed25519, mldsa, mlkem, x25519
from rich.console import Console
from rich.measure import Measurement
from rich.progress import Progress
from rich.table import Table
from rich.text import Text

from antireplay import epochs
from antireplay.audit import AuditLog, reanchor, shown, verify
from antireplay.audit import tail as audit_tail_records
from antireplay.cli.dds import dds
from antireplay.cli.demo import StepResult, run_gateway_demo, run_window_demo
from antireplay.cli.mavlink_pq import mavlink_pq
from antireplay.config import AppConfig
from antireplay.core.counters import DEFAULT_WINDOW
from antireplay.core.errors import AntiReplayError, ConfigError, ReplayAttackError, StateFileError
from antireplay.core.messages import MessageType
from antireplay.rcan.auth import (
    SDK_PRIVATE_MAGIC,
    PrivateKey,
    SdkKeyPair,
    UnsignedFieldsError,
    load_public_key,
    sdk_key_id,
    sign_envelope,
    sign_sdk,
    write_key_pair,
)
from antireplay.rcan.envelope import parse, safety_class
from antireplay.state import ceilings
from antireplay.state.durable import read_kind, repair
from antireplay.wiring import Allowed

if TYPE_CHECKING:
    from antireplay.mavlink import Role

console = Console()
#: Importing these registers their state reseeders for ``state repair``.
STATE_OWNERS = (ceilings, epochs)
KEY_TYPES: dict[str, Any] = {
    "ed25519": ed25519.Ed25519PrivateKey,
    "ml-dsa-65": mldsa.MLDSA65PrivateKey,
    "ml-dsa-87": mldsa.MLDSA87PrivateKey,
    "ml-kem-1024": mlkem.MLKEM1024PrivateKey,  # a vehicle's key for `mavlink-pq`
    "x25519": x25519.X25519PrivateKey,  # a vehicle's hybrid key for `mavlink-pq`
}


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


@click.group(cls=_Cli)
@click.version_option(package_name="antireplay")
def main() -> None:
    """Stop captured robot and drone commands from working twice."""


main.add_command(dds)


def _fail(message: str, code: int = 2) -> NoReturn:
    """One line on stderr, never wrapped (newlines in a message are flattened)."""
    click.echo("antireplay: error: " + " ".join(message.split()), err=True)
    sys.exit(code)


def _load_config(path: Path | None, state_dir: Path) -> AppConfig:
    from antireplay.http.gateway import embedded_default  # noqa: PLC0415 - keeps `--help` fast

    try:
        return AppConfig.from_yaml(path) if path is not None else embedded_default(state_dir)
    except ConfigError as exc:
        _fail(str(exc))
    except OSError as exc:
        _fail(f"state directory {state_dir}: {exc.strerror or exc}")


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


def _check_audit_anchor(path: Path) -> None:
    """What opening the trail would refuse, found read-only (nothing written, nothing adopted)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        _fail(f"audit {path}: cannot create its directory ({exc.strerror or exc})")
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
    from antireplay.http.gateway import resolve_upstream  # noqa: PLC0415
    from antireplay.state import open_store  # noqa: PLC0415
    from antireplay.wiring import build_registry  # noqa: PLC0415

    importable_cwd(config.upstream)
    try:
        build_registry(config)
        for kid, pem in config.jwt.keys.items():
            try:
                load_public_key(Path(pem).read_bytes())
            except (OSError, ValueError) as exc:
                allowed = f"a readable PEM public key ({exc})"
                raise ConfigError(f"jwt.keys.{kid}", pem, allowed) from None
        resolve_upstream(config.upstream, config.upstream_timeout_s)
    except ConfigError as exc:
        _fail(str(exc))
    _check_audit_file(Path(config.audit), f"audit: {_MOVE_ASIDE}")
    _check_audit_anchor(Path(config.audit))
    try:
        if config.store.startswith("sqlite:"):
            from antireplay.state.sqlite import check_readable  # noqa: PLC0415

            check_readable(config.store[len("sqlite:") :])  # read-only: nothing used up
        else:
            store = open_store(config.store)
            try:
                store.ready()  # reaches it: the PING and eviction check serve's first commit runs
            finally:
                store.close()
    except ConfigError as exc:
        _fail(str(exc))
    except Exception as exc:  # any backend's own failure, named with its spec
        _fail(f"store {config.store}: cannot open it ({type(exc).__name__}: {exc})")


@main.command()
@click.option("--config", "config_path", type=click.Path(path_type=Path), default=None)
@click.option("--host", default="127.0.0.1", show_default=True)
@click.option("--port", default=8080, show_default=True, type=click.IntRange(0, 65535))
@click.option("--state-dir", default=Path(".antireplay"), type=click.Path(path_type=Path))
@click.option("--access-log", is_flag=True, help="Log every request on stdout (uvicorn's log).")
@click.option(
    "--ssl-certfile",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Serve HTTPS with this PEM certificate (chain); needs --ssl-keyfile.",
)
@click.option(
    "--ssl-keyfile",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="The certificate's PEM private key.",
)
def serve(  # noqa: PLR0917 - one option per knob
    config_path: Path | None,
    host: str,
    port: int,
    state_dir: Path,
    access_log: bool,
    ssl_certfile: Path | None,
    ssl_keyfile: Path | None,
) -> None:
    """Run the HTTP gateway (embedded default without --config).

    Prints one line once it listens: ``listening on http(s)://HOST:PORT (store ..., audit
    ...)``; ``GET /healthz`` is liveness, ``GET /readyz`` readiness (store and audit)."""
    import socket  # noqa: PLC0415

    import uvicorn  # noqa: PLC0415
    from uvicorn.config import LOGGING_CONFIG  # noqa: PLC0415

    from antireplay.http.gateway import create_app  # noqa: PLC0415

    if (ssl_certfile is None) != (ssl_keyfile is None):
        raise click.UsageError("give --ssl-certfile and --ssl-keyfile together")
    config = _load_config(config_path, state_dir)
    preflight(config)
    try:
        app = create_app(config)
    except ConfigError as exc:
        _fail(str(exc))
    except sqlite3.DatabaseError as exc:
        _fail(f"{config.audit} or {config.store}: {exc}")
    log_config: dict[str, Any] = json.loads(json.dumps(LOGGING_CONFIG))  # a deep copy
    log_config["loggers"]["uvicorn.error"]["level"] = "WARNING"
    settings = uvicorn.Config(
        app,
        log_config=log_config,
        access_log=access_log,
        timeout_graceful_shutdown=10,
        ssl_certfile=None if ssl_certfile is None else str(ssl_certfile),
        ssl_keyfile=None if ssl_keyfile is None else str(ssl_keyfile),
    )
    if ssl_certfile is not None:
        try:  # a bad certificate or key fails here, as one line naming both, before listening
            settings.load()
        except (OSError, ValueError) as exc:
            _fail(
                f"--ssl-certfile {ssl_certfile} / --ssl-keyfile {ssl_keyfile}: not a PEM "
                f"certificate (chain) and its unencrypted PEM private key ({exc})"
            )
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.create_server((host, port), family=family)  # a busy port: one line (OSError)
    bound = sock.getsockname()[1]
    scheme = "https" if ssl_certfile is not None else "http"
    where = f"[{host}]" if family == socket.AF_INET6 else host
    click.echo(
        f"listening on {scheme}://{where}:{bound} "
        f"(store {_without_secrets(config.store)}, audit {config.audit})"
    )
    uvicorn.Server(settings).run(sockets=[sock])


def _without_secrets(spec: str) -> str:
    """A store spec fit to print: the user and password of a URL are masked."""
    scheme, sep, rest = spec.partition("://")
    userinfo, at, location = rest.rpartition("@")
    return f"{scheme}{sep}***@{location}" if sep and at and userinfo else spec


def _table(results: list[StepResult], title: str) -> Table:
    table = Table(title=title)
    for column in ("step", "expected", "got", ""):
        table.add_column(column)
    for r in results:
        table.add_row(r.step, r.expected, r.got, "[green]ok[/green]" if r.ok else "[red]MISMATCH")
    return table


@main.command()
@click.option("--in-process", is_flag=True, help="Only the §8.3 window, no gateway process.")
def demo(in_process: bool) -> None:
    """Play operator and attacker; exit non-zero if any answer differs."""
    if in_process:
        results = run_window_demo()
        console.print(_table(results, "antireplay demo: RCAN §8.3 window (in process)"))
        chain_ok = True
    else:
        with console.status("starting a gateway on a free loopback port…"):
            results, report = run_gateway_demo()
        console.print(_table(results, "antireplay demo: gateway on loopback, SQLite state"))
        chain_ok = report.ok
        verdict = "[green]intact[/green]" if report.ok else f"[red]broken at {report.broken_at}"
        console.print(f"audit chain: {report.records} records, {verdict}")
    failed = [r for r in results if not r.ok]
    if failed or not chain_ok:
        console.print(f"[red]{len(failed)} step(s) differ[/red]")
        sys.exit(1)
    console.print(f"[green]all {len(results)} steps behaved as expected[/green]")


@main.command()
@click.option("--alg", type=click.Choice(sorted(KEY_TYPES)), default="ed25519", show_default=True)
@click.option("--out", required=True, type=click.Path(path_type=Path), help="File prefix.")
def keygen(alg: str, out: Path) -> None:
    """Write PREFIX.key.pem (mode 0600) and PREFIX.pub.pem."""
    key = KEY_TYPES[alg].generate()
    private = out.with_name(out.name + ".key.pem")
    public = out.with_name(out.name + ".pub.pem")
    try:
        write_key_pair(key, private, public)
    except FileExistsError:
        _fail(f"{private} exists; refusing to overwrite a key")
    console.print(f"[green]{alg} key pair:[/green] {private} {public}")


#: What ``sign --key`` accepts, for its errors.
_SIGNING_KEYS = "an unencrypted PEM private key (Ed25519, ML-DSA-65 or ML-DSA-87)"
_SDK_KEYS = "an unencrypted PEM ML-DSA-65 private key or an RCAN SDK key file (MLDSAKeyPair.save)"
#: The sizes of an ML-DSA-65 key pair (FIPS 204), as the SDK's key file holds them.
_SDK_KEY_SIZES = (1952, 4032)


def _private_key(
    paths: tuple[Path, ...], accepted: str = _SIGNING_KEYS
) -> PrivateKey | tuple[PrivateKey, ...]:
    keys = []
    for path in paths:
        try:
            key = serialization.load_pem_private_key(path.read_bytes(), None)
        except (ValueError, TypeError) as exc:
            _fail(f"--key {path}: not {accepted} ({exc})")
        if not isinstance(key, PrivateKey):
            _fail(f"--key {path}: a {type(key).__name__}; accepted: {accepted}")
        keys.append(key)
    return keys[0] if len(keys) == 1 else tuple(keys)


@main.command()
@click.option(
    "--key",
    "key_paths",
    multiple=True,
    required=True,
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
)
@click.option("--kid", default=None, help="Required, except with --sdk (the key's SDK key id).")
@click.option("--alg", default="ed25519", show_default=True)
@click.option(
    "--sdk",
    is_flag=True,
    help="Sign as the RCAN SDK's sign_message does (ML-DSA-65; its verify_message accepts it).",
)
@click.option("--json", "json_file", type=click.File("r"), help="Base message (JSON file or -).")
@click.option("--cmd", default=None)
@click.option("--target", default=None)
@click.option(
    "--param", "params", multiple=True, help="key=value (value parsed as JSON if it can be)"
)
@click.option("--type", "msg_type", type=int, default=None)
@click.option("--safety-event", default=None)
@click.option("--scope", default=None)
def sign(  # noqa: PLR0917 - one option per envelope field
    key_paths: tuple[Path, ...],
    kid: str | None,
    alg: str,
    sdk: bool,
    json_file: Any,
    cmd: str | None,
    target: str | None,
    params: tuple[str, ...],
    msg_type: int | None,
    safety_event: str | None,
    scope: str | None,
) -> None:
    """Build and sign an envelope (fresh msg_id and timestamp unless given); print it."""
    try:
        body: Any = json.load(json_file) if json_file is not None else {}
    except ValueError as exc:
        _fail(f"--json {json_file.name}: not JSON ({exc})")
    if not isinstance(body, dict):
        _fail(f"--json {json_file.name}: a JSON object is needed, got {type(body).__name__}")
    body.setdefault("rcan", "3.2")
    body.setdefault("rcan_version", "3.2")
    body.setdefault("msg_id", str(uuid.uuid4()))
    if "timestamp_ms" not in body:
        body.setdefault("timestamp", round(time.time(), 6))
    extra = {"cmd": cmd, "target": target, "type": msg_type, "safety_event": safety_event}
    body.update({k: v for k, v in {**extra, "scope": scope}.items() if v is not None})
    for item in params:
        name, _, raw = item.partition("=")
        try:
            value: Any = json.loads(raw)
        except ValueError:
            value = raw
        body.setdefault("params", {})[name] = value
    try:
        if sdk:
            signed = sign_sdk(body, _sdk_key(key_paths, kid))
        elif kid is None:
            _fail("--kid is required (except with --sdk)")
        else:
            signed = sign_envelope(body, kid, alg, _private_key(key_paths))
    except (ValueError, ReplayAttackError) as exc:
        hint = ""
        if isinstance(exc, UnsignedFieldsError) and {"type", "safety_event", "scope"} & set(
            exc.fields
        ):
            hint = "; with --sdk, --cmd ESTOP/STOP/RESUME is a safety message"
        _fail(f"cannot sign: {exc}{hint}")
    click.echo(json.dumps(signed))


def _sdk_key(paths: tuple[Path, ...], kid: str | None) -> mldsa.MLDSA65PrivateKey | SdkKeyPair:
    """One ML-DSA-65 key for ``sign --sdk``: a PEM key, or the RCAN SDK's own key file
    (``MLDSAKeyPair.save``; signed with the SDK, which must be installed)."""
    if len(paths) != 1:
        _fail("--sdk signs with exactly one --key (ML-DSA-65)")
    data = paths[0].read_bytes()
    key: mldsa.MLDSA65PrivateKey | SdkKeyPair
    if data.startswith(SDK_PRIVATE_MAGIC):
        size = int.from_bytes(data[4:6], "big")
        if (size, len(data) - 6 - size) != _SDK_KEY_SIZES:
            _fail(f"--key {paths[0]}: a damaged RCAN SDK key file; accepted: {_SDK_KEYS}")
        try:  # the SDK signs its own files with dilithium-py (``rcan[pq]``)
            from rcan.signing import MLDSAKeyPair  # noqa: PLC0415 - only for the SDK's files

            importlib.import_module("dilithium_py.ml_dsa")
        except ImportError as exc:
            _fail(
                f"--key {paths[0]}: an RCAN SDK key file, and the SDK cannot sign with it here "
                f"({exc}); install it: pip install 'rcan[pq]' (or give a PEM ML-DSA-65 key)"
            )
        key = MLDSAKeyPair.load(paths[0])
        key_id = key.key_id
    else:
        pem = _private_key(paths, _SDK_KEYS)
        if not isinstance(pem, mldsa.MLDSA65PrivateKey):
            _fail(
                f"--key {paths[0]}: the RCAN SDK signs with ML-DSA-65 only; accepted: {_SDK_KEYS}"
            )
        key, key_id = pem, sdk_key_id(pem.public_key())
    if kid is not None and kid != key_id:
        _fail(f"--kid {kid}: the SDK signs with the key's SDK key id, {key_id}")
    return key


@main.command()
@click.argument("url")
@click.argument("message", type=click.File("rb"), default="-")
@click.option("--bearer", default=None, help="JWT for the Authorization header.")
def send(url: str, message: Any, bearer: str | None) -> None:
    """POST a signed envelope to a gateway and print the verdict (exit 1 if refused)."""
    headers = {"content-type": "application/json"}
    if bearer:
        headers["authorization"] = f"Bearer {bearer}"
    if not url.rstrip("/").endswith("/v1/messages"):
        url = url.rstrip("/") + "/v1/messages"
    raw = message.read()
    try:
        reply = httpx.post(url, content=raw, headers=headers, timeout=10)
    except httpx.HTTPError as exc:
        _fail(f"cannot reach {url}: {exc}")
    table = Table(title=f"{url} answered HTTP {reply.status_code}", caption=_sent_as(raw))
    table.add_column("field")
    table.add_column("value")
    try:
        body = reply.json()
    except ValueError:
        body = {"body": reply.text[:200]}
    for name, value in body.items():
        table.add_row(str(name), json.dumps(value) if not isinstance(value, str) else value)
    console.print(table)
    sys.exit(0 if reply.status_code < 300 else 1)


def _sent_as(raw: bytes) -> str | None:
    """How the gateway classes what was sent (``cmd ESTOP as SAFETY/ESTOP``): the answer
    does not say, and the class sets the window and the scope a key needs."""
    try:
        env = parse(raw)
    except ReplayAttackError:
        return None  # the gateway's answer says what is wrong with it
    kind, event = safety_class(env)
    try:
        name = MessageType(kind).name
    except ValueError:
        name = str(kind)
    return f"sent cmd {env.cmd} as {name}" + (f"/{event}" if event else "")


@main.group()
def audit() -> None:
    """The hash-chained audit trail."""


_HEAD_KEY = click.option(
    "--head-key", type=click.Path(path_type=Path), default=None, help="Default: PATH.key"
)
_HEAD_FILE = click.option(
    "--head", "head_file", type=click.Path(path_type=Path), default=None, help="Default: PATH.head"
)


@audit.command("verify")
@click.argument("path", type=click.Path(exists=True, path_type=Path))
@_HEAD_KEY
@_HEAD_FILE
def audit_verify(path: Path, head_key: Path | None, head_file: Path | None) -> None:
    """Check the hash chain and the head checkpoint; say what is proven and what is not.

    Exits 1 on a broken chain, truncation, rewrite or a missing/forged checkpoint."""
    _check_audit_file(path, _OPEN_ONLY_AUDIT)
    try:
        report = verify(path, head_key=head_key, head_path=head_file)
    except StateFileError as exc:
        _fail(str(exc))
    for line in report.lines():
        click.echo(line)  # never wrapped: scripts and operators grep these lines
    if not report.ok:
        sys.exit(1)


@audit.command("reanchor")
@click.argument("path", type=click.Path(exists=True, path_type=Path))
@_HEAD_KEY
@_HEAD_FILE
def audit_reanchor(path: Path, head_key: Path | None, head_file: Path | None) -> None:
    """Accept the current intact chain as the new head (after checking it with verify)."""
    try:
        report = reanchor(path, head_key=head_key, head_path=head_file)
    except StateFileError as exc:
        _fail(str(exc))
        return
    console.print(f"re-anchored {path} at row {report.checkpoint_rows}", markup=False)


@audit.command("tail")
@click.argument("path", type=click.Path(exists=True, path_type=Path))
@click.option("-n", "count", default=20, show_default=True, type=click.IntRange(min=0))
@click.option("--json", "as_json", is_flag=True, help="One JSON object per line.")
def audit_tail(path: Path, count: int, as_json: bool) -> None:
    """Print the most recent records (a table, never truncated; or JSON lines)."""
    _check_audit_file(path, _OPEN_ONLY_AUDIT)
    try:
        records = audit_tail_records(path, count)  # read-only: tail never writes the trail
    except StateFileError as exc:
        _fail(str(exc))
    rows = [shown(r) for r in records]
    if as_json:
        for row in rows:
            click.echo(json.dumps(row, separators=(",", ":")))
        return
    table = Table(title=str(path))
    for column in ("seq", "time (UTC)", "outcome", "code", "warning", "type", "sender", "msg_id"):
        table.add_column(column, overflow="fold")
    for row in rows:
        sender = row["sender"] or "-"  # a row with no sender (STATE_LOST, a memo hit)
        sender += "" if row["sender"] is None or row["sender_verified"] else " (claimed)"
        cells = (row["seq"], row["time"], row["outcome"], row["code"], row["warning"],
                 row["msg_type"], sender, row["msg_id"])  # fmt: skip
        table.add_row(*(Text("" if v is None else str(v)) for v in cells))
    out = console
    if not console.is_terminal:  # a pipe or a file: as wide as the table, nothing cut
        wide = Console(width=1_000_000)
        out = Console(width=max(80, Measurement.get(wide, wide.options, table).maximum))
    out.print(table)


@main.group()
def config() -> None:
    """Configuration tools."""


@config.command("check")
@click.argument("path", type=click.Path(path_type=Path))
def config_check(path: Path) -> None:
    """Validate a YAML config: everything ``serve`` checks (keys, store, audit, upstream)."""
    try:
        cfg = AppConfig.from_yaml(path)
    except ConfigError as exc:
        _fail(str(exc))
    preflight(cfg)
    console.print_json(data=cfg.model_dump())
    if not cfg.keys:
        click.echo(f"antireplay: warning: {path} configures no keys: no signature can verify, "
                   "so every command will be refused", err=True)  # fmt: skip
    click.echo(f"ok: {len(cfg.keys)} keys, store {cfg.store}, audit {cfg.audit}")


@main.command()
@click.argument("names", nargs=-1)
def bench(names: tuple[str, ...]) -> None:
    """Run the benchmarks (from a source checkout) and print their ratio tables."""
    available = sorted(p.stem for p in Path("benchmarks").glob("bench_*.py"))
    if not available:
        _fail("no benchmarks/ here: run `antireplay bench` from a source checkout")
    unknown = [n for n in names if n not in available and f"bench_{n}" not in available]
    if unknown:
        _fail(f"unknown benchmark {', '.join(unknown)}; available: {', '.join(available)}")
    chosen = [n for n in available if not names or n in names or n.removeprefix("bench_") in names]
    outputs = []
    with Progress(console=console) as progress:
        task = progress.add_task("benchmarks", total=len(chosen))
        for name in chosen:
            progress.update(task, description=name)
            run = subprocess.run(
                [sys.executable, "-m", f"benchmarks.{name}"],
                capture_output=True,
                text=True,
                check=False,
            )
            outputs.append((name, run.returncode, run.stdout + run.stderr[-2000:]))
            progress.advance(task)
    for name, code, text in outputs:
        console.rule(f"{name} {'' if code == 0 else f'(exit {code})'}")
        console.print(text, markup=False, highlight=False)
    if any(code for _, code, _ in outputs):
        sys.exit(1)


@main.group()
def state() -> None:
    """Crash-safe state files (counters, epochs)."""


@state.command("repair")
@click.argument("path", type=click.Path(path_type=Path))
@click.option(
    "--kind",
    type=click.Choice(["nonce-counter", "epoch-signer"]),
    help="State kind; read from the file when it is still legible.",
)
def state_repair(path: Path, kind: str | None) -> None:
    """Reseed a damaged state file safely above anything that could have been used."""
    kind = kind or read_kind(path)
    if kind is None:
        _fail(f"cannot tell what {path} holds; pass --kind")
        return
    try:
        reseeded = repair(path, kind)
    except StateFileError as exc:  # e.g. the file's owner is still running
        _fail(str(exc))
        return
    console.print(f"[green]repaired {path} ({kind})[/green]")
    console.print_json(data=reseeded)


def _signing_key(path: Path) -> bytes:
    """The link key: exactly 32 raw bytes (taken as they are: a raw key may begin or end
    with a whitespace byte), or 64 hex characters with optional surrounding whitespace."""
    try:
        raw = path.read_bytes()
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
        lines = path.read_text().splitlines()
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


@main.command("mavlink-router")
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
    default=None,
    help="This vehicle's system id: frames addressed elsewhere, and frames from it reflected "
    "back from a ground link, are refused.",
)
@click.option("--store", "store_spec", default="sqlite:.antireplay/mavlink.db", show_default=True)
@click.option("--audit", "audit_path", default=".antireplay/mavlink-audit.db", show_default=True)
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
    system_id: int | None,
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
    import signal  # noqa: PLC0415

    from antireplay.state import open_store  # noqa: PLC0415
    from antireplay.wiring import (  # noqa: PLC0415
        RouterOptions,
        build_mavlink_router,
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
        audit_log = AuditLog(audit_path)
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
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    try:
        router.start()  # claims each guard's lease, waiting out a crashed run's (seconds)
    except ReplayAttackError as exc:
        _fail(f"--store {store_spec}: {exc}")
    roles = ", ".join(f"{role} {text}" for role, text, _ in endpoints)
    console.print(f"[green]mavlink-router {roles} (system id {system_id})[/green]")
    done.wait()
    router.stop()
    audit_log.close()
    store.close()


main.add_command(mavlink_router, "mavlink-proxy")  # the command's first name, kept
main.add_command(mavlink_pq)


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
