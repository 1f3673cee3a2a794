"""``state repair``: reseed a damaged crash-safe state file (counters, epochs) safely."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from antireplay import epochs
from antireplay.core.errors import StateFileError
from antireplay.state import ceilings
from antireplay.state.durable import read_kind, repair

if TYPE_CHECKING:
    pass

from antireplay.cli._common import _fail, console

#: Importing these registers their state reseeders for ``state repair``.
STATE_OWNERS = (ceilings, epochs)


@click.group()
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
