"""The ``antireplay`` command line (click + rich): a thin adapter over the library.

Errors are for people: an ordinary mistake (a bad option value, a missing or
foreign file, a busy port, a configuration ``serve`` would refuse) is one line
on stderr, ``antireplay: error: <what> (<what is allowed>)``, never wrapped,
with exit status 2, and never a traceback.  :class:`_Cli` gives click's own
usage errors that shape too.  ``config check`` runs the same :func:`preflight`
as ``serve``, so a configuration that passes the check starts.
"""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any, NoReturn

import click
import httpx
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ed25519, mldsa
from rich.console import Console
from rich.progress import Progress
from rich.table import Table

from antireplay import counters, epochs
from antireplay.audit import AuditLog, reanchor, verify
from antireplay.audit import tail as audit_tail_records
from antireplay.auth import PrivateKey, load_public_key, sign_envelope, write_key_pair
from antireplay.config import AppConfig
from antireplay.counters import DEFAULT_WINDOW
from antireplay.dds.cli import dds
from antireplay.demo import StepResult, run_gateway_demo, run_window_demo
from antireplay.durable import read_kind, repair
from antireplay.errors import AntiReplayError, ConfigError, ReplayAttackError, StateFileError

console = Console()
#: Importing these registers their state reseeders for ``state repair``.
STATE_OWNERS = (counters, epochs)
KEY_TYPES: dict[str, Any] = {
    "ed25519": ed25519.Ed25519PrivateKey,
    "ml-dsa-65": mldsa.MLDSA65PrivateKey,
    "ml-dsa-87": mldsa.MLDSA87PrivateKey,
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
    from antireplay.gateway import embedded_default  # noqa: PLC0415 - keeps `--help` fast

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


def preflight(config: AppConfig) -> None:
    """Every check ``serve`` makes before it listens; exits with one line on the first failure."""
    from antireplay.gateway import resolve_upstream  # noqa: PLC0415
    from antireplay.stores import open_store  # noqa: PLC0415
    from antireplay.wiring import build_registry  # noqa: PLC0415

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
            from antireplay.stores.sqlite import check_readable  # noqa: PLC0415

            check_readable(config.store[len("sqlite:") :])  # read-only: nothing used up
        else:
            open_store(config.store).close()
    except ConfigError as exc:
        _fail(str(exc))
    except Exception as exc:  # any backend's own failure, named with its spec
        _fail(f"store {config.store}: cannot open it ({type(exc).__name__}: {exc})")


@main.command()
@click.option("--config", "config_path", type=click.Path(path_type=Path), default=None)
@click.option("--host", default="127.0.0.1", show_default=True)
@click.option("--port", default=8080, show_default=True, type=click.IntRange(0, 65535))
@click.option("--state-dir", default=Path(".antireplay"), type=click.Path(path_type=Path))
def serve(config_path: Path | None, host: str, port: int, state_dir: Path) -> None:
    """Run the HTTP gateway (embedded default without --config)."""
    import uvicorn  # noqa: PLC0415

    from antireplay.gateway import create_app  # noqa: PLC0415

    config = _load_config(config_path, state_dir)
    preflight(config)
    try:
        app = create_app(config)
    except ConfigError as exc:
        _fail(str(exc))
    except sqlite3.DatabaseError as exc:
        _fail(f"{config.audit} or {config.store}: {exc}")
    uvicorn.run(app, host=host, port=port, log_level="warning", timeout_graceful_shutdown=10)


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


def _private_key(paths: tuple[Path, ...]) -> PrivateKey | tuple[PrivateKey, ...]:
    keys = []
    for path in paths:
        try:
            key = serialization.load_pem_private_key(path.read_bytes(), None)
        except (ValueError, TypeError) as exc:
            _fail(f"--key {path}: not an unencrypted PEM private key ({exc})")
        if not isinstance(key, PrivateKey):
            _fail(f"--key {path}: unsupported key type {type(key).__name__}")
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
@click.option("--kid", required=True)
@click.option("--alg", default="ed25519", show_default=True)
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
    kid: str,
    alg: str,
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
        signed = sign_envelope(body, kid, alg, _private_key(key_paths))
    except (ValueError, ReplayAttackError) as exc:
        _fail(f"cannot sign: {exc}")
    click.echo(json.dumps(signed))


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
    try:
        reply = httpx.post(url, content=message.read(), headers=headers, timeout=10)
    except httpx.HTTPError as exc:
        _fail(f"cannot reach {url}: {exc}")
    table = Table(title=f"{url} answered HTTP {reply.status_code}")
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
def audit_tail(path: Path, count: int) -> None:
    """Print the most recent records."""
    _check_audit_file(path, _OPEN_ONLY_AUDIT)
    table = Table(title=str(path))
    for column in ("seq", "time (UTC)", "outcome", "code", "warning", "type", "sender", "msg_id"):
        table.add_column(column)
    try:
        records = audit_tail_records(path, count)  # read-only: tail never writes the trail
    except StateFileError as exc:
        _fail(str(exc))
    for r in records:
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(r.at))
        sender = f"{r.sender}" + ("" if r.sender_verified else " (claimed)")
        row = (r.seq, when, r.outcome, r.code, r.warning, r.msg_type, sender, r.msg_id)
        table.add_row(*("" if v is None else str(v) for v in row))
    console.print(table)


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


def _udp(spec: str) -> tuple[str, int]:
    scheme, _, rest = spec.partition(":")
    host, _, port = rest.rpartition(":")
    if scheme != "udp" or not host or not (port.isascii() and port.isdigit()) or int(port) > 65535:
        raise click.BadParameter(f"{spec!r}: expected udp:HOST:PORT with PORT 0..65535")
    return host, int(port)


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


@main.command("mavlink-proxy")
@click.option("--listen", required=True, help="udp:HOST:PORT the ground station talks to")
@click.option("--forward", required=True, help="udp:HOST:PORT of the vehicle (or SITL)")
@click.option("--key-file", required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "--system-id",
    type=click.IntRange(1, 255),
    default=None,
    help="This vehicle's system id: frames addressed elsewhere, and frames from it reflected "
    "back to the listen port, are refused.",
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
    "--allow-unsigned",
    multiple=True,
    type=click.IntRange(0, 2**24 - 1),
    help="Message id allowed unsigned.",
)
@click.option(
    "--reorder-window",
    type=click.IntRange(0, DEFAULT_WINDOW),
    default=0,
    show_default=True,
    help="Accept out-of-order timestamps within this many (0: strictly increasing).",
)
@click.option(
    "--write-through",
    is_flag=True,
    help="Write every accepted timestamp to the store before forwarding (several proxies "
    "active at once on one store); default: persist every second behind a lease and a "
    "restart fence.",
)
def mavlink_proxy(  # noqa: PLR0917 - one option per knob
    listen: str,
    forward: str,
    key_file: Path,
    system_id: int | None,
    store_spec: str,
    audit_path: str,
    metrics_port: int | None,
    allow_unsigned: tuple[int, ...],
    reorder_window: int,
    write_through: bool,
) -> None:
    """Forward only MAVLink v2 frames the guard accepts, both directions."""
    import signal  # noqa: PLC0415

    from antireplay.stores import open_store  # noqa: PLC0415
    from antireplay.wiring import build_mavlink_proxy, serve_proxy_metrics  # noqa: PLC0415

    key = _signing_key(key_file)
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
        proxy = build_mavlink_proxy(
            _udp(listen), _udp(forward), key, store, audit_log, system_id=system_id,
            allow_unsigned=frozenset(allow_unsigned), reorder_window=reorder_window,
            write_through=write_through,
        )  # fmt: skip
    except OSError as exc:
        _fail(f"--listen {listen} / --forward {forward}: {exc.strerror or exc}")
    if metrics_port is not None:
        serve_proxy_metrics(proxy, metrics_port)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    try:
        proxy.start()  # claims each guard's lease, waiting out a crashed run's (seconds)
    except ReplayAttackError as exc:
        _fail(f"--store {store_spec}: {exc}")
    console.print(f"[green]mavlink-proxy {listen} -> {forward} (system id {system_id})[/green]")
    done.wait()
    proxy.stop()
    audit_log.close()
    store.close()
