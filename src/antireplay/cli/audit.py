"""``audit verify``, ``audit head``, ``audit reanchor`` and ``audit tail``: the audit trail
for operators."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import click
from rich.console import Console
from rich.measure import Measurement
from rich.table import Table
from rich.text import Text

from antireplay.audit import export_head, reanchor, shown, verify
from antireplay.audit import tail as audit_tail_records
from antireplay.core.errors import StateFileError

if TYPE_CHECKING:
    pass

from antireplay.cli._common import _OPEN_ONLY_AUDIT, _check_audit_file, _fail, console
from antireplay.cli._token import KeyOrUri
from antireplay.cli._token import head_key as open_head_key


@click.group()
def audit() -> None:
    """The hash-chained audit trail."""


_HEAD_KEY = click.option(
    "--head-key",
    type=KeyOrUri(exists=False),
    default=None,
    help="Default: PATH.key; or the head key in a token (pkcs11:token=...;object=...).",
)
_HEAD_FILE = click.option(
    "--head", "head_file", type=click.Path(path_type=Path), default=None, help="Default: PATH.head"
)


def _recorded(name: str, text: str) -> Callable[[Callable[..., None]], Callable[..., None]]:
    """An option naming an existing file that records a head (``--state``, ``--since``)."""
    kind = click.Path(exists=True, dir_okay=False, path_type=Path)
    return click.option(f"--{name}", name, type=kind, default=None, help=text)


@audit.command("verify")
@click.argument("path", type=click.Path(exists=True, path_type=Path))
@_HEAD_KEY
@_HEAD_FILE
@_recorded("state", "The SQLite state database: prove the trail extends the head it recorded.")
@_recorded("since", "A head exported by `audit head --export`: prove the trail extends it.")
def audit_verify(
    path: Path, head_key: Path | str | None, head_file: Path | None, state: Path | None,
    since: Path | None,
) -> None:  # fmt: skip
    """Check the hash chain and the head checkpoint; say what is proven and what is not.

    Exits 1 on a broken chain, truncation, rewrite or a missing/forged checkpoint, and
    (AUDIT_ROLLED_BACK) on a trail that does not extend the head the state database or
    an exported head recorded."""
    _check_audit_file(path, _OPEN_ONLY_AUDIT)
    try:
        report = verify(
            path, head_key=open_head_key(head_key), head_path=head_file, state=state, since=since
        )
    except StateFileError as exc:
        _fail(str(exc))
    for line in report.lines():
        click.echo(line)  # never wrapped: scripts and operators grep these lines
    if not report.ok:
        sys.exit(1)


@audit.command("head")
@click.argument("path", type=click.Path(exists=True, path_type=Path))
@_HEAD_KEY
@_HEAD_FILE
@click.option(
    "--export",
    "export",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Write the verified head, MACed with the head key, to this file (keep it elsewhere).",
)
def audit_head(
    path: Path, head_key: Path | str | None, head_file: Path | None, export: Path
) -> None:
    """Export the trail's verified head; `audit verify --since FILE` later proves the
    trail extends it (a rollback, truncation or rewrite before it fails)."""
    _check_audit_file(path, _OPEN_ONLY_AUDIT)
    try:
        report = export_head(path, export, head_key=open_head_key(head_key), head_path=head_file)
    except StateFileError as exc:
        _fail(str(exc))
        return
    click.echo(f"exported the head of {path} at row {report.checkpoint_rows} to {export}")


@audit.command("reanchor")
@click.argument("path", type=click.Path(exists=True, path_type=Path))
@_HEAD_KEY
@_HEAD_FILE
def audit_reanchor(path: Path, head_key: Path | str | None, head_file: Path | None) -> None:
    """Accept the current intact chain as the new head (after checking it with verify)."""
    try:
        report = reanchor(path, head_key=open_head_key(head_key), head_path=head_file)
    except StateFileError as exc:
        _fail(str(exc))
        return
    console.print(f"re-anchored {path} at row {report.checkpoint_rows}", markup=False)


@audit.command("tail")
@click.argument("path", type=click.Path(exists=True, path_type=Path))
@click.option(
    "-n",
    "count",
    default=20,
    show_default=True,
    type=click.IntRange(min=0),
    help="How many of the latest records to show.",
)
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
