"""The audit verifier: recompute the chain, check the anchored head, reanchor on request.

What it proves and what it cannot is in :mod:`antireplay.audit`.
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path

from antireplay.audit.chain import (
    _ALL,
    _FIELDS,
    GENESIS,
    HeadAnchor,
    _aside,
    _compare,
    _connect,
    _digest,
    _last,
    _wrongly_typed,
)
from antireplay.core.errors import AuditFileError


@dataclass(frozen=True)
class ChainReport:
    """Result of :func:`verify`: what the chain and the head checkpoint prove."""

    records: int
    broken_at: int | None
    reason: str | None
    #: "match", "missing" (no checkpoint), "no-key" (MAC not checkable), or the mismatch.
    head: str = "match"
    checkpoint_rows: int | None = None
    after_checkpoint: int = 0

    @property
    def chain_ok(self) -> bool:
        return self.broken_at is None

    @property
    def ok(self) -> bool:
        """The chain links and a genuine checkpoint matches it (no truncation, no rewrite)."""
        return self.broken_at is None and self.head == "match"

    def lines(self) -> list[str]:
        """What was proven and what was not, one fact per line."""
        out = [
            f"chain intact to row {self.records} ({self.records} records)"
            if self.chain_ok
            else f"chain broken at row {self.broken_at}: {self.reason}"
        ]
        if self.head == "match":
            out.append(f"head checkpoint matches row {self.checkpoint_rows} (MAC verified)")
            if self.after_checkpoint:
                out.append(
                    f"rows after the last checkpoint: {self.after_checkpoint} "
                    "(not covered by the head MAC: a crash before the checkpoint, or appended "
                    "without the key)"
                )
        elif self.head == "missing":
            out.append("head checkpoint missing: cannot prove the newest rows were not deleted")
        elif self.head == "no-key":
            out.append("head key missing: the checkpoint's MAC cannot be checked")
        else:
            out.append(f"head checkpoint does not match: {self.head}")
        return out


def verify(
    path: str | Path, *, head_key: str | Path | None = None, head_path: str | Path | None = None
) -> ChainReport:
    """Recompute the hash chain and check it against the head checkpoint (read-only).

    A file that is not an audit trail raises ``AuditFileError``; a missing, damaged or
    forged checkpoint or key is *reported* in ``head`` (the report says what is provable)."""
    path = Path(path)
    anchor = HeadAnchor(path, Path(head_key) if head_key else None,
                        Path(head_path) if head_path else None)  # fmt: skip
    db = _connect(path, read_only=True)
    try:
        chain = _walk(db)
        try:
            key = anchor.load_key()
            checkpoint = anchor.read(key)
        except AuditFileError as exc:
            return ChainReport(*chain, head=f"{exc.path}: {exc.problem}")
        if checkpoint is None:
            return ChainReport(*chain, head="missing")
        if key is None:
            return ChainReport(*chain, head="no-key", checkpoint_rows=checkpoint.rows)
        problem = _compare(db, checkpoint)
    except sqlite3.DatabaseError as exc:
        raise AuditFileError(
            str(path), f"unreadable audit trail ({exc})", recovery=_aside(path)
        ) from None
    finally:
        db.close()
    if problem is not None:
        return ChainReport(*chain, head=problem, checkpoint_rows=checkpoint.rows)
    after = max(0, chain[0] - checkpoint.rows)
    return ChainReport(*chain, checkpoint_rows=checkpoint.rows, after_checkpoint=after)


def _walk(db: sqlite3.Connection) -> tuple[int, int | None, str | None]:
    """(records, first broken row, reason) from recomputing every link."""
    prev, expected_seq, count = GENESIS, 1, 0
    for values in db.execute(_ALL):
        count += 1
        row = dict(zip(_FIELDS, values[:9], strict=True))
        wrong = _wrongly_typed(row)
        if wrong is not None:
            return count, expected_seq, f"invalid {wrong}: a value antireplay never writes"
        if row["seq"] != expected_seq:
            return count, expected_seq, "record missing or reordered"
        if values[9] != prev:
            return count, row["seq"], "prev_hash does not link"
        if values[10] != _digest(prev, row):
            return count, row["seq"], "record contents changed"
        prev, expected_seq = values[10], expected_seq + 1
    return count, None, None


def reanchor(
    path: str | Path, *, head_key: str | Path | None = None, head_path: str | Path | None = None
) -> ChainReport:
    """Accept the current, intact chain as the new head (after an operator checked it).

    Creates a new key when the old one is gone (a damaged or exposed key is replaced,
    never reused).  Refuses a broken chain."""
    path = Path(path)
    anchor = HeadAnchor(path, Path(head_key) if head_key else None,
                        Path(head_path) if head_path else None)  # fmt: skip
    try:
        key = anchor.load_key()
    except AuditFileError:
        key = None
        anchor.key_path.unlink()  # a damaged key is replaced, never reused
    key = key if key is not None else anchor.create_key()
    db = _connect(path, read_only=True)
    try:
        chain = _walk(db)
        if chain[1] is not None:
            raise AuditFileError(
                str(path), f"chain broken at row {chain[1]}: {chain[2]}; cannot re-anchor",
                recovery=_aside(path),
            )  # fmt: skip
        seq, head = _last(db)
    finally:
        db.close()
    anchor.write(key, seq, head)
    return ChainReport(*chain, checkpoint_rows=seq)
