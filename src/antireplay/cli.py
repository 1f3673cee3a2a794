"""The ``antireplay`` command line (click + rich): a thin adapter over the library."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import click
import httpx
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ed25519, mldsa
from rich.console import Console
from rich.progress import Progress
from rich.table import Table

from antireplay import counters, epochs
from antireplay.audit import AuditLog, verify
from antireplay.auth import PrivateKey, sign_envelope, write_key_pair
from antireplay.clock import SystemClock
from antireplay.config import AppConfig
from antireplay.dds.cli import dds
from antireplay.demo import StepResult, run_gateway_demo, run_window_demo
from antireplay.durable import read_kind, repair
from antireplay.errors import ConfigError, ReplayAttackError
from antireplay.pipeline import TokenBucket

console = Console()
#: Importing these registers their state reseeders for ``state repair``.
STATE_OWNERS = (counters, epochs)
KEY_TYPES: dict[str, Any] = {
    "ed25519": ed25519.Ed25519PrivateKey,
    "ml-dsa-65": mldsa.MLDSA65PrivateKey,
    "ml-dsa-87": mldsa.MLDSA87PrivateKey,
}


@click.group()
@click.version_option(package_name="antireplay")
def main() -> None:
    """Stop captured robot and drone commands from working twice."""


main.add_command(dds)


def _fail(message: str, code: int = 2) -> None:
    console.print(f"[red]{message}[/red]")
    sys.exit(code)


def _load_config(path: Path | None, state_dir: Path) -> AppConfig:
    from antireplay.gateway import embedded_default  # noqa: PLC0415 - keeps `--help` fast

    try:
        return AppConfig.from_yaml(path) if path is not None else embedded_default(state_dir)
    except ConfigError as exc:
        _fail(str(exc))
        raise


@main.command()
@click.option("--config", "config_path", type=click.Path(path_type=Path), default=None)
@click.option("--host", default="127.0.0.1", show_default=True)
@click.option("--port", default=8080, show_default=True, type=int)
@click.option("--state-dir", default=Path(".antireplay"), type=click.Path(path_type=Path))
def serve(config_path: Path | None, host: str, port: int, state_dir: Path) -> None:
    """Run the HTTP gateway (embedded default without --config)."""
    import uvicorn  # noqa: PLC0415

    from antireplay.gateway import create_app  # noqa: PLC0415

    config = _load_config(config_path, state_dir)
    try:
        app = create_app(config)
    except ConfigError as exc:
        _fail(str(exc))
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
        key = serialization.load_pem_private_key(path.read_bytes(), None)
        if not isinstance(key, PrivateKey):
            _fail(f"{path}: unsupported key type {type(key).__name__}")
            raise SystemExit(2)
        keys.append(key)
    return keys[0] if len(keys) == 1 else tuple(keys)


@main.command()
@click.option("--key", "key_paths", multiple=True, required=True, type=click.Path(path_type=Path))
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
    body: dict[str, Any] = json.load(json_file) if json_file is not None else {}
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


@audit.command("verify")
@click.argument("path", type=click.Path(exists=True, path_type=Path))
def audit_verify(path: Path) -> None:
    """Check the hash chain; report the first broken link."""
    report = verify(path)
    if report.ok:
        console.print(f"[green]chain intact: {report.records} records[/green]")
        return
    _fail(f"chain broken at record {report.broken_at}: {report.reason}", 1)


@audit.command("tail")
@click.argument("path", type=click.Path(exists=True, path_type=Path))
@click.option("-n", "count", default=20, show_default=True)
def audit_tail(path: Path, count: int) -> None:
    """Print the most recent records."""
    table = Table(title=str(path))
    for column in ("seq", "time (UTC)", "outcome", "code", "warning", "type", "sender", "msg_id"):
        table.add_column(column)
    for r in AuditLog(path).tail(count):
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
    """Validate a YAML config with the same errors as the library."""
    try:
        cfg = AppConfig.from_yaml(path)
    except ConfigError as exc:
        _fail(str(exc))
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
    type=click.Choice(["nonce-counter", "epoch-signer", "epoch-verifier"]),
    help="State kind; read from the file when it is still legible.",
)
def state_repair(path: Path, kind: str | None) -> None:
    """Reseed a damaged state file safely above anything that could have been used."""
    kind = kind or read_kind(path)
    if kind is None:
        _fail(f"cannot tell what {path} holds; pass --kind")
        return
    reseeded = repair(path, kind)
    console.print(f"[green]repaired {path} ({kind})[/green]")
    console.print_json(data=reseeded)


def _udp(spec: str) -> tuple[str, int]:
    scheme, _, rest = spec.partition(":")
    host, _, port = rest.rpartition(":")
    if scheme != "udp" or not host or not port.isdigit():
        raise click.BadParameter(f"{spec!r}: expected udp:HOST:PORT")
    return host, int(port)


def _signing_key(path: Path) -> bytes:
    raw = path.read_bytes().strip()
    if len(raw) == 64:
        try:
            return bytes.fromhex(raw.decode())
        except ValueError:
            pass
    if len(raw) != 32:
        raise click.BadParameter(f"{path}: a 32-byte key, raw or as 64 hex characters")
    return raw


@main.command("mavlink-proxy")
@click.option("--listen", required=True, help="udp:HOST:PORT the ground station talks to")
@click.option("--forward", required=True, help="udp:HOST:PORT of the vehicle (or SITL)")
@click.option("--key-file", required=True, type=click.Path(exists=True, path_type=Path))
@click.option("--system-id", type=int, default=None, help="This vehicle's system id (binding).")
@click.option("--store", "store_spec", default="sqlite:.antireplay/mavlink.db", show_default=True)
@click.option("--audit", "audit_path", default=".antireplay/mavlink-audit.db", show_default=True)
@click.option("--metrics-port", type=int, default=None, help="Serve Prometheus metrics here.")
@click.option("--allow-unsigned", multiple=True, type=int, help="Message id allowed unsigned.")
@click.option("--reorder-window", type=int, default=0, show_default=True)
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
) -> None:
    """Forward only MAVLink v2 frames the guard accepts, both directions."""
    import signal  # noqa: PLC0415

    from antireplay.mavlink import MavlinkGuard, MavlinkProxy  # noqa: PLC0415
    from antireplay.stores import open_store  # noqa: PLC0415

    key = _signing_key(key_file)
    store = open_store(store_spec)
    audit_log = AuditLog(audit_path)
    common: dict[str, Any] = {
        "store": store, "allow_unsigned": frozenset(allow_unsigned),
        "reorder_window": reorder_window,
    }  # fmt: skip
    inbound = MavlinkGuard(key, system_id=system_id, store_prefix="mav-in", **common)
    outbound = MavlinkGuard(key, store_prefix="mav-out", **common)
    bucket = TokenBucket(50.0, SystemClock())

    def audit_reject(direction: str, exc: ReplayAttackError, raw: bytes) -> None:
        if not bucket.take():
            return
        sender = f"mav:{raw[5]}/{raw[6]}" if len(raw) > 6 else None
        audit_log.append(
            at=time.time(), outcome="rejected", code=str(exc.code), warning=direction,
            msg_type=None, sender=sender, sender_verified=False, msg_id=None,
        )  # fmt: skip

    proxy = MavlinkProxy(_udp(listen), _udp(forward), inbound, outbound, audit_reject)
    if metrics_port is not None:
        _serve_proxy_metrics(proxy, metrics_port)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    proxy.start()
    console.print(f"[green]mavlink-proxy {listen} -> {forward} (system id {system_id})[/green]")
    done.wait()
    proxy.stop()
    audit_log.close()
    store.close()


def _serve_proxy_metrics(proxy: Any, port: int) -> None:
    from prometheus_client import REGISTRY, start_http_server  # noqa: PLC0415
    from prometheus_client.core import CounterMetricFamily  # noqa: PLC0415

    class ProxyCollector:
        def collect(self) -> Any:
            forwarded = CounterMetricFamily(
                "antireplay_mavlink_forwarded", "Frames forwarded", labels=["direction"]
            )
            for direction, n in proxy.stats.forwarded.items():
                forwarded.add_metric([direction], n)
            dropped = CounterMetricFamily(
                "antireplay_mavlink_dropped", "Frames dropped", labels=["direction", "code"]
            )
            for label, n in proxy.stats.dropped.items():
                direction, _, code = label.partition(":")
                dropped.add_metric([direction, code], n)
            yield forwarded
            yield dropped

    REGISTRY.register(ProxyCollector())
    start_http_server(port, addr="127.0.0.1")
