"""Read-only checks of a SQLite state database: what decodes, what is refused and how to recover.

Theory of operation
-------------------
A file that is not a readable database, a meta row or a stored expiry that does not
decode (a hand-edited row) is refused with a ``StateFileError`` naming the file and the
recovery: move it aside, and the next start fences what it held.  :func:`check_readable`
runs these checks opening the file read-only, so a ``config check`` never uses up the
loss detection of the store's next real open; the store (:mod:`.sqlite`) runs them at
open and decodes its meta row with :func:`decode_meta`.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Final

from antireplay.core.errors import StateFileError
from antireplay.state import _codec
from antireplay.state.loss import MetaRow

META_SELECT: Final = "SELECT deployment, generation, watermark, fence, data_loss_events FROM meta"
#: Stored expiries that are not numbers: SQLite orders every number before any text or
#: blob, so the index finds them at once (a REAL column keeps what it cannot convert).
_SEEN_UNDECODABLE: Final = "SELECT key, expires FROM seen WHERE expires >= '' LIMIT 1"


def check_readable(path: str | Path) -> None:
    """Refuse a file that is not a readable database, or whose meta row or expiries do not
    decode, without writing anything (so a ``config check`` never uses up the loss
    detection of the store's next real open)."""
    path = Path(path)
    if not path.exists():
        return
    recovery = move_aside(path)
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master")}
            if {"meta", "seen"} <= tables:
                _check_rows(db, path, recovery)
        finally:
            db.close()
    except sqlite3.Error as exc:
        raise StateFileError(
            str(path), f"not a readable replay-state database ({exc})", recovery=recovery
        ) from None


def move_aside(path: Path) -> str:
    """The recovery from a damaged database: the next start fences what it held."""
    return f"mv {path} {path}.corrupt (the next start re-creates it behind a restart fence)"


def _check_rows(db: sqlite3.Connection, path: Path, recovery: str) -> None:
    """Every stored expiry is a number and the meta row decodes (or ``StateFileError``)."""
    bad = db.execute(_SEEN_UNDECODABLE).fetchone()
    if bad is not None:
        key = f"seen {bad[0]!r} expiry"
        raise _codec.undecodable(bad[1], "a number", where=str(path), key=key, recovery=recovery)
    row = db.execute(META_SELECT).fetchone()
    if row is not None:
        decode_meta(row, path, recovery)


def decode_meta(row: tuple[object, ...], path: Path, recovery: str) -> MetaRow:
    """The meta row's values, each what its column holds (or ``StateFileError``)."""
    deployment, generation, watermark, fence, losses = row
    where = str(path)
    return (
        _codec.decode_hex(deployment, 32, where=where, key="meta deployment", recovery=recovery),
        _codec.decode_int(generation, where=where, key="meta generation", recovery=recovery),
        _codec.decode_float(watermark, where=where, key="meta watermark", recovery=recovery),
        _codec.decode_float(fence, where=where, key="meta fence", recovery=recovery),
        _codec.decode_int(losses, where=where, key="meta data_loss_events", recovery=recovery),
    )
