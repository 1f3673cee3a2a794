"""The ``antireplay`` command line (click + rich): a thin adapter over the library."""

from __future__ import annotations

import sys
from pathlib import Path

import click
from rich.console import Console
from rich.table import Table

from antireplay import counters, epochs
from antireplay.config import SecurityConfig
from antireplay.demo import run_window_demo
from antireplay.durable import read_kind, repair
from antireplay.errors import ConfigError

console = Console()
#: Importing these registers their state reseeders for ``state repair``.
STATE_OWNERS = (counters, epochs)


@click.group()
@click.version_option(package_name="antireplay")
def main() -> None:
    """Stop captured robot and drone commands from working twice."""


@main.command()
def demo() -> None:
    """Play operator and attacker against a receiver; exit non-zero if any answer differs."""
    results = run_window_demo()
    table = Table(title="antireplay demo: RCAN §8.3 freshness window + msg_id seen-set")
    table.add_column("step")
    table.add_column("expected")
    table.add_column("got")
    table.add_column("")
    for r in results:
        mark = "[green]ok[/green]" if r.ok else "[red]MISMATCH[/red]"
        table.add_row(r.step, r.expected, r.got, mark)
    console.print(table)
    failed = [r for r in results if not r.ok]
    if failed:
        console.print(f"[red]{len(failed)} step(s) differ[/red]")
        sys.exit(1)
    console.print(f"[green]all {len(results)} steps behaved as expected[/green]")


@main.group()
def config() -> None:
    """Configuration tools."""


@config.command("check")
@click.argument("path", type=click.Path(path_type=Path))
def config_check(path: Path) -> None:
    """Validate a YAML config with the same errors as the library."""
    try:
        cfg = SecurityConfig.from_yaml(path)
    except ConfigError as exc:
        console.print(f"[red]{exc}[/red]")
        sys.exit(2)
    console.print_json(data=cfg.model_dump())


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
        console.print(f"[red]cannot tell what {path} holds; pass --kind[/red]")
        sys.exit(2)
    reseeded = repair(path, kind)
    console.print(f"[green]repaired {path} ({kind})[/green]")
    console.print_json(data=reseeded)
