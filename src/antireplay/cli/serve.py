"""``serve``, ``config check``, ``demo`` and ``bench``: the gateway and its checks.

``serve --workers N`` runs N gateway processes under uvicorn's supervisor (spawned, each
building its own app from the same configuration, see :func:`worker_app`), accepting on
the one listening socket the parent bound.  They share the store and the audit trail on
disk: the store's commit is the one atomic step, so of two processes racing a msg_id
exactly one accepts it, and the audit writer chains inside ``BEGIN IMMEDIATE``, so the
processes extend one chain.  A memory store is refused above one process (its seen-set
would be one process's).  Metrics are per process.

Keys reload without a restart (:mod:`antireplay.wiring.keys`): ``SIGHUP`` to a one-process
``serve``, or ``antireplay keys reload`` (every process and replica on the state; with
``--workers`` a ``SIGHUP`` to the supervisor is uvicorn's own: it replaces the workers one
by one).  A file that does not load keeps the old keys and logs one line.
"""

from __future__ import annotations

import gc
import json
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

import click
from rich.progress import Progress
from rich.table import Table

from antireplay.cli.demo import StepResult, run_gateway_demo, run_window_demo
from antireplay.config import AppConfig, KeyConfig
from antireplay.core.errors import AntiReplayError, ConfigError, StateUnavailableError

if TYPE_CHECKING:
    from types import FrameType

    from starlette.applications import Starlette

from antireplay.cli._common import _fail, _load_config, console, preflight, until_stopped


@click.command()
@click.option(
    "--config",
    "config_path",
    type=click.Path(path_type=Path),
    default=None,
    help="YAML configuration (keys, store, audit, upstream); without it, the embedded default.",
)
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to listen on.")
@click.option(
    "--port",
    default=8080,
    show_default=True,
    type=click.IntRange(0, 65535),
    help="Port to listen on (0: any free port, printed).",
)
@click.option(
    "--state-dir",
    default=Path(".antireplay"),
    show_default=True,
    type=click.Path(path_type=Path),
    help="Where the embedded default keeps its store, audit trail and demo keys.",
)
@click.option("--access-log", is_flag=True, help="Log every request on stdout (uvicorn's log).")
@click.option(
    "--workers",
    default=1,
    show_default=True,
    type=click.IntRange(1, 64),
    help="Gateway processes on the one listening socket, sharing the store and audit trail "
    "(a SQLite or Redis store; refused with the memory store).",
)
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
def serve(  # noqa: PLR0915, PLR0917 - one option per knob, start-up in order
    config_path: Path | None,
    host: str,
    port: int,
    state_dir: Path,
    access_log: bool,
    workers: int,
    ssl_certfile: Path | None,
    ssl_keyfile: Path | None,
) -> None:
    """Run the HTTP gateway (embedded default without --config).

    Prints one line once it listens: "listening on http(s)://HOST:PORT (store ..., anchor
    ..., audit ...)" ("no state anchor" and a warning for a SQLite store without one),
    then "fenced until T (...): why" while a fence lies ahead (a state with no history);
    GET /healthz is liveness, GET /readyz readiness (store and audit)."""
    import socket  # noqa: PLC0415

    # A SIGHUP during start-up waits (blocked, pending) for the reload handler: never the
    # default action (exit); a pending one reloads once the handler is in place.
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGHUP})

    import uvicorn  # noqa: PLC0415
    from uvicorn.config import LOGGING_CONFIG  # noqa: PLC0415
    from uvicorn.supervisors import Multiprocess  # noqa: PLC0415

    from antireplay.http.app import fence_notice  # noqa: PLC0415
    from antireplay.wiring import anchor_summary, create_app  # noqa: PLC0415

    if (ssl_certfile is None) != (ssl_keyfile is None):
        raise click.UsageError("give --ssl-certfile and --ssl-keyfile together")
    config = _load_config(config_path, state_dir)
    preflight(config)
    try:
        shared_state(config, workers)
        app = create_app(config, reload=reloader(config_path, state_dir))
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
        f"(store {config.store_spec.redacted()}, {anchor_summary(config)}"
        f"audit {config.audit})"
    )
    for warning in _startup_warnings(config, anchor_summary(config)):
        click.echo(f"antireplay: warning: {warning}", err=True)
    fenced = fence_notice(app.state.receiver)
    if fenced is not None:  # a state with no history, or a loss noticed at open
        click.echo(fenced)
    if workers == 1:
        settled_heap()
        _take_sighup(lambda _n, _f: app.state.keys.request_reload())  # a pending one reloads
        with until_stopped(lambda: f"served {_served(app)}"):
            uvicorn.Server(settings).run(sockets=[sock])
        app.state.keys.stop()
        return
    _release(app)  # it only checked the configuration: each worker builds its own
    building = {"config": config_path, "state_dir": state_dir}
    os.environ[_SERVE_ENV] = json.dumps(building, default=str)
    settings = uvicorn.Config(
        f"{__name__}:worker_app", factory=True, workers=workers, log_config=log_config,
        access_log=access_log, timeout_graceful_shutdown=10,
        ssl_certfile=settings.ssl_certfile, ssl_keyfile=settings.ssl_keyfile,
    )  # fmt: skip
    click.echo(f"{workers} worker processes (metrics per process)")
    # the workers read the file fresh; until uvicorn's supervisor takes SIGHUP it is a no-op
    _take_sighup(lambda _n, _f: None)  # unblocked first: the workers must not inherit the mask
    Multiprocess(settings, sockets=[sock]).run()  # its own handlers stop the workers
    click.echo(f"stopped: {workers} worker processes ended (counts were per process)", err=True)


def _take_sighup(handler: Callable[[int, FrameType | None], None]) -> None:
    """Install ``handler`` for SIGHUP, then unblock it (blocked since the command began):
    a SIGHUP sent during start-up is delivered now, to the handler."""
    signal.signal(signal.SIGHUP, handler)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGHUP})


#: The startup's short form of ``config check``'s no-anchor warning (said in full there).
NO_ANCHOR_REFERENCE = (
    "no state anchor: a restored snapshot can re-open replays (see `antireplay config check`, "
    "docs/threat-model.md#the-state-anchor)"
)


def _startup_warnings(config: AppConfig, summary: str) -> list[str]:
    """``config check``'s anchor warnings, the long no-anchor one as a short reference."""
    from antireplay.wiring import anchor_warnings  # noqa: PLC0415

    if summary.startswith("no state anchor"):
        return [NO_ANCHOR_REFERENCE]
    return anchor_warnings(config)


def _served(app: Starlette) -> str:
    """What a gateway answered since it started, for its shutdown line."""
    registry = app.state.metrics.registry
    accepted = registry.get_sample_value("antireplay_accepted_total") or 0
    refused = sum(
        sample.value
        for metric in registry.collect()
        for sample in metric.samples
        if sample.name == "antireplay_rejected_total"
    )
    return f"{accepted:g} accepted, {refused:g} refused"


#: How ``serve --workers`` tells its spawned workers which configuration to build.
_SERVE_ENV = "ANTIREPLAY_SERVE_WORKER"


def shared_state(config: AppConfig, workers: int) -> None:
    """``ConfigError`` if ``workers`` processes cannot share ``config``'s store: a memory
    store is one process's (another process would accept the same msg_id again)."""
    if workers > 1 and config.store_spec.backend == "memory":
        raise ConfigError(
            "store", config.store, "a sqlite: or redis:// store with --workers > 1 (a memory "
            "store is one process's: another process would accept the same message again)",
        )  # fmt: skip


def worker_app() -> Starlette:
    """One ``serve --workers`` process's app (uvicorn's factory, in the spawned worker)."""
    from antireplay.wiring import create_app  # noqa: PLC0415

    settings = json.loads(os.environ[_SERVE_ENV])
    path = None if settings["config"] is None else Path(settings["config"])
    state_dir = Path(settings["state_dir"])
    app = create_app(_load_config(path, state_dir), reload=reloader(path, state_dir))
    settled_heap()
    return app


def reloader(path: Path | None, state_dir: Path) -> Callable[[], AppConfig]:
    """What a keys reload re-reads (raises, never exits: it runs on the watcher's thread)."""
    from antireplay.wiring import embedded_default  # noqa: PLC0415

    return lambda: AppConfig.from_yaml(path) if path is not None else embedded_default(state_dir)


def settled_heap() -> None:
    """Put what startup built (modules, the app, keys, the store) out of the cyclic
    collector's sight (``gc.freeze``): it lives as long as the process, and a full
    collection under a flood then scans only what requests left behind.  Scanning it all
    was a 30 ms pause that a fresh ESTOP waited out (``benchmarks gateway``, ESTOP row)."""
    gc.collect()
    gc.freeze()


def _release(app: Starlette) -> None:
    """Close what building ``app`` opened (its audit trail and store)."""
    receiver = app.state.receiver
    app.state.keys.stop()
    receiver.close()
    receiver.cache.store.close()


def _table(results: list[StepResult], title: str) -> Table:
    table = Table(title=title)
    for column in ("step", "expected", "got", ""):
        table.add_column(column)
    for r in results:
        table.add_row(r.step, r.expected, r.got, "[green]ok[/green]" if r.ok else "[red]MISMATCH")
    return table


@click.command()
@click.option("--in-process", is_flag=True, help="Only the §8.3 window, no gateway process.")
def demo(in_process: bool) -> None:
    """Play operator and attacker; exit non-zero if any answer differs."""
    with until_stopped(lambda: "the demo did not finish, so it has no verdict"):
        _demo(in_process)


def _demo(in_process: bool) -> None:
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


@click.group()
def config() -> None:
    """Configuration tools."""


@config.command("check")
@click.argument("path", type=click.Path(path_type=Path))
@click.option(
    "--verbose", is_flag=True, help="Also print the whole configuration, defaults filled in."
)
def config_check(path: Path, verbose: bool) -> None:
    """Validate a YAML config: every section's keys and values; everything serve checks
    (keys, store, audit), and that an HTTP upstream answers a connection; the router's and
    each PQ end's keys and allow-lists when their section is there; the DDS key file."""
    from antireplay.wiring import anchor_warnings, build_anchor  # noqa: PLC0415

    try:
        cfg = AppConfig.from_yaml(path)
        sections = _check_sections(cfg)
        anchor = build_anchor(cfg)
        if anchor is not None:
            try:
                anchor.ping()  # reaches it (serve would start unready without it)
            finally:
                anchor.close()
    except (ConfigError, StateUnavailableError) as exc:
        _fail(str(exc))
    preflight(cfg)
    _probe_upstream(cfg.upstream, cfg.upstream_timeout_s)
    if verbose:
        console.print_json(data=cfg.model_dump())
    others = {"mavlink", "mavlink_pq"} & cfg.model_fields_set or cfg.dds is not None
    if not cfg.keys and not others:  # a file for the router, a PQ end or DDS needs none
        click.echo(f"antireplay: warning: {path} configures no keys: no signature can verify, "
                   "so every command will be refused", err=True)  # fmt: skip
    for warning in [
        *anchor_warnings(cfg),
        *_sdk_key_hints(cfg),
        *_shared_key_warnings(cfg),
        *expiry_warnings(cfg),
    ]:
        click.echo(f"antireplay: warning: {warning}", err=True)
    click.echo(f"ok: {len(cfg.keys)} keys, store {cfg.store}, audit {cfg.audit}")
    for line in sections:
        click.echo(f"ok: {line}")


def _check_sections(cfg: AppConfig) -> list[str]:
    """What the commands other than ``serve`` would load from their sections (key files,
    allow-lists, PEM keys), loaded and dropped: nothing opened, nothing bound."""
    from antireplay.wiring.leaves import check_head_key, check_state  # noqa: PLC0415
    from antireplay.wiring.mavlink import router_endpoints, router_options  # noqa: PLC0415
    from antireplay.wiring.mavlink_pq import ground_end, vehicle_end  # noqa: PLC0415

    said = []
    given = cfg.model_fields_set
    if check_head_key(cfg):
        said.append("audit.head_key: the token logs in and holds the key")
    if "mavlink" in given and cfg.mavlink.vehicle:
        endpoints = router_endpoints(cfg.mavlink)
        router_options(cfg.mavlink)
        spec = cfg.mavlink.store_spec
        try:
            check_state(spec)
        except AntiReplayError:
            raise  # names the file and the recovery
        except Exception as exc:  # any backend's own failure, named with its key
            allowed = f"a store that opens ({type(exc).__name__}: {exc})"
            raise ConfigError("mavlink.store", spec.redacted(), allowed) from None
        said.append(f"mavlink: {len(endpoints)} endpoints, store {cfg.mavlink.store}")
    pq = cfg.mavlink_pq
    if "mavlink_pq" in given and "ground" in pq.model_fields_set:
        ground_end(pq.ground)
        said.append("mavlink_pq.ground: keys load")
    if "mavlink_pq" in given and "vehicle" in pq.model_fields_set:
        vehicle_end(pq.vehicle)
        said.append(f"mavlink_pq.vehicle: keys load, {len(pq.vehicle.peers)} peers")
    if cfg.dds is not None:
        cfg.dds.psk()
        said.append(f"dds: domain {cfg.dds.domain_id}, key file {cfg.dds.psk_file}")
    return said


def _sdk_key_hints(cfg: AppConfig) -> list[str]:
    """Without ``sdk_compat``, a key given as the RCAN SDK's own public key file: the SDK
    signs under the key's SDK key id, which then names no key (401 UNKNOWN_SENDER)."""
    from antireplay.rcan.auth import load_public_key, sdk_key_id  # noqa: PLC0415

    if cfg.sdk_compat:
        return []
    hints = []
    for entry in cfg.keys:
        raw = Path(entry.public_keys[0]).read_bytes()  # preflight read them all
        if entry.alg == "ml-dsa-65" and not raw.lstrip().startswith(b"-----BEGIN"):
            hints.append(
                f"keys.{entry.kid} is an RCAN SDK public key file: the SDK signs as its SDK key "
                f"id {sdk_key_id(load_public_key(raw))}, which names a key only with "
                "sdk_compat: true (else 401 UNKNOWN_SENDER)"
            )
    return hints


def _shared_key_warnings(cfg: AppConfig) -> list[str]:
    """One public key under two kids: legal (a rename), but both kids are one key to revoke,
    and ``keys revoke`` of either refuses both."""
    from antireplay.rcan.auth import load_public_key  # noqa: PLC0415

    first: dict[bytes, str] = {}
    said = []
    for entry in cfg.keys:
        for path in entry.public_keys:
            raw = load_public_key(Path(path).read_bytes()).public_bytes_raw()
            other = first.setdefault(raw, entry.kid)
            if other != entry.kid:
                said.append(
                    f"keys.{entry.kid} and keys.{other} are one public key ({path}): revoking "
                    "either refuses both"
                )
    return said


#: ``config check`` warns of a key that expires within this many days.
EXPIRY_WARNING_DAYS = 14


def expiry_warnings(cfg: AppConfig, now: float | None = None) -> list[str]:
    """Keys expired, or expiring within :data:`EXPIRY_WARNING_DAYS` (rotate them now)."""
    now = time.time() if now is None else now
    said = []
    for entry in cfg.keys:
        end = KeyConfig.seconds(entry.not_after)
        if end is None or end - now > EXPIRY_WARNING_DAYS * 86400:
            continue
        when = entry.not_after.isoformat() if entry.not_after else ""
        state = "expired" if end <= now else f"expires in {(end - now) / 86400:.1f} days"
        said.append(f"keys.{entry.kid} {state} (not_after {when}): rotate it (docs/operations.md)")
    return said


def _probe_upstream(upstream: str | None, timeout_s: float) -> None:
    """An ``http(s)://`` upstream must accept a connection (``serve`` starts without it, but
    every accepted message would then be answered ``UPSTREAM_FAILED``)."""
    if upstream is None or not upstream.startswith(("http://", "https://")):
        return
    url = urlsplit(upstream)
    try:
        port = url.port or (443 if url.scheme == "https" else 80)
        socket.create_connection((url.hostname or "", port), timeout=min(timeout_s, 3.0)).close()
    except (OSError, ValueError) as exc:
        _fail(f"upstream {upstream}: cannot connect ({getattr(exc, 'strerror', None) or exc})")


@click.command()
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
