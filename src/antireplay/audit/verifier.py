"""The audit verifier: recompute the chain across segments, check the anchored head,
reanchor on request.

What it proves and what it cannot is in :mod:`antireplay.audit`; how segments link and
what retention may remove is in :mod:`.segments`.  Each segment kept is walked in order:
its link must start where the previous segment ends (and carry the head key's MAC), its
rows must chain; the oldest segment's link is the proven cut point retention left.
Given the state database (``state``) or an exported head (``since``), it also proves the
trail extends the head recorded there (:mod:`.consistency`): a trail rolled back, truncated
or rewritten before it fails.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from os import PathLike
from pathlib import Path
from typing import TypeVar

from antireplay.audit import consistency, segments
from antireplay.audit.chain import (
    _ALL,
    _FIELDS,
    GENESIS,
    Checkpoint,
    HeadAnchor,
    HeadKey,
    MacKey,
    _aside,
    _connect,
    _digest,
    _link,
    _wrongly_typed,
)
from antireplay.audit.consistency import Consistency
from antireplay.core.errors import AuditFileError
from antireplay.state.outbox import read_trail_head

T = TypeVar("T")


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
    #: Segments kept, and where the chain kept starts (segment, row, the hash it chains from).
    segments: int = 1
    first_segment: int = 1
    first_row: int = 1
    first_hash: str = GENESIS
    #: The last row kept (``records`` when nothing was removed); ``None``: none walked yet.
    last_row: int | None = None
    #: The trail against heads recorded elsewhere: the state database's, an exported one.
    state: Consistency | None = None
    since: Consistency | None = None
    #: Why a recorded head could not be compared (no state record, no key).
    unproven: tuple[str, ...] = ()

    @property
    def chain_ok(self) -> bool:
        return self.broken_at is None

    @property
    def ok(self) -> bool:
        """The chain links and a genuine checkpoint matches it (no truncation, no rewrite),
        and it extends every head recorded elsewhere that was given."""
        extended = all(c is None or c.ok for c in (self.state, self.since))
        return self.broken_at is None and self.head == "match" and extended

    def lines(self) -> list[str]:
        """What was proven and what was not, one fact per line."""
        out = []
        if self.first_segment > 1:
            removed = "1" if self.first_segment == 2 else f"1–{self.first_segment - 1}"
            out.append(
                f"segments {removed} removed by retention; "
                f"chain verified from row {self.first_row} / hash {self.first_hash}"
            )
        last = self.records if self.last_row is None else self.last_row
        kept = f"{self.records} records" + (
            f" in {self.segments} segments" if self.segments > 1 else ""
        )
        out.append(
            f"chain intact to row {last} ({kept})"
            if self.chain_ok
            else f"chain broken at row {self.broken_at}: {self.reason}"
        )
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
        for name, found in (("state database", self.state), ("exported head", self.since)):
            if found is None:
                continue
            if found.problem is not None:
                out.append(f"{consistency.ROLLED_BACK}: against the {name}: {found.problem}")
            elif found.cut is not None:
                out.append(f"{name} at row {found.head.rows}: not comparable: {found.cut}")
            else:
                out.append(f"{name} at row {found.head.rows}: the chain extends it (MAC verified)")
        out.extend(self.unproven)
        return out


class _Trail:
    """Every segment kept, oldest first, the live one last: the live one held open (it cannot
    rotate under the walk), each rotated one opened in turn (a long trail, few descriptors)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.live = _connect(path, read_only=True)
        try:
            self.files = [file for _, file in segments.rotated(path)] + [path]
            self.links = [self._with(file, _link) for file in self.files]
        except BaseException:
            self.live.close()
            raise

    def _with(self, file: Path, read: Callable[[sqlite3.Connection], T]) -> T:
        """``read`` on one segment, its database errors naming the file."""
        db = self.live if file == self.path else _connect(file, read_only=True)
        try:
            return read(db)
        except sqlite3.DatabaseError as exc:
            raise AuditFileError(
                str(file), f"unreadable audit trail ({exc})", recovery=_aside(file)
            ) from None
        finally:
            if db is not self.live:
                db.close()

    def close(self) -> None:
        self.live.close()

    def check_order(self, first: int) -> None:
        segments.check_order(self.path, list(zip(self.files, self.links, strict=True)), first)

    def walk(self, key: HeadKey | None) -> tuple[ChainReport, str]:
        """Recompute every link of every segment, oldest first; the report and the last
        hash that links."""
        start = self.links[0]
        report = ChainReport(0, None, None, segments=len(self.files), first_segment=start.n,
                             first_row=start.first, first_hash=start.prev)  # fmt: skip
        prev, expected, count = start.prev, start.first, 0
        for file, link in zip(self.files, self.links, strict=True):
            problem = None
            if (link.first, link.prev) != (expected, prev):
                problem = f"{file.name} does not start where the segment before it ends"
            elif key is not None and not HeadAnchor.link_ok(key, link):
                problem = f"{file.name}: segment link MAC does not verify (forged, or another key)"
            if problem is not None:
                return replace(report, records=count, broken_at=expected, reason=problem), prev
            walked, broken, reason, prev = self._with(
                file, partial(_walk, prev=prev, start=expected)
            )
            count += walked
            if broken is not None:
                where = f" (in {file.name})" if len(self.files) > 1 else ""
                failed = replace(report, records=count, broken_at=broken, reason=f"{reason}{where}")
                return failed, prev
            expected += walked
        return replace(report, records=count, last_row=expected - 1), prev

    def compare(self, checkpoint: Checkpoint) -> str | None:
        """The checkpoint against the segment holding its row (or starting right after it)."""
        return self._with(self.path, partial(segments.compare, self.path, checkpoint=checkpoint))


def verify(
    path: str | PathLike[str],
    *,
    head_key: str | Path | MacKey | None = None,
    head_path: str | Path | None = None,
    state: str | Path | None = None,
    since: str | Path | None = None,
) -> ChainReport:
    """Recompute the hash chain across segments and check it against the head checkpoint
    (read-only); with ``state`` (a SQLite state database) or ``since`` (an exported head),
    prove the trail extends the head recorded there.

    A file that is not an audit trail, or a segment missing, renamed or out of order, raises
    ``AuditFileError``; a missing, damaged or forged checkpoint or key is *reported* in
    ``head`` (the report says what is provable); so is a rollback against a recorded head.
    An export that is not one, or forged, raises ``AuditFileError``."""
    report = _verify(Path(path), head_key, head_path)
    if state is None and since is None:
        return report
    anchor = HeadAnchor(Path(path), head_key)
    key = anchor.load_key()
    if key is None:
        return replace(report, unproven=("head key missing: recorded heads not compared",))
    trail = _Trail(Path(path))
    try:
        unproven: tuple[str, ...] = ()
        found = None
        if state is not None:
            recorded = _state_head(Path(state))
            found = consistency.against_state(trail.path, trail.live, recorded, key)
            if recorded is None:
                unproven = (f"state database {state}: no trail head recorded yet",)
        exported = None
        if since is not None:
            head = consistency.read_export(Path(since), key, trail.path)
            if head is None:
                raise AuditFileError(str(since), "does not exist", recovery="give an exported head")
            exported = consistency.extends(trail.path, trail.live, head)
    finally:
        trail.close()
    return replace(report, state=found, since=exported, unproven=unproven)


def _state_head(path: Path) -> consistency.TrailHead | None:
    """The trail head the SQLite state database at ``path`` records."""
    try:
        return read_trail_head(path)
    except sqlite3.DatabaseError as exc:
        raise AuditFileError(
            str(path),
            f"not a readable SQLite state database ({exc})",
            recovery="give the state database the gateway uses (state: sqlite:PATH)",
        ) from None


def _verify(
    path: Path, head_key: str | Path | MacKey | None, head_path: str | Path | None
) -> ChainReport:
    """:func:`verify` without recorded heads."""
    anchor = HeadAnchor(path, head_key,
                        Path(head_path) if head_path else None)  # fmt: skip
    trail = _Trail(path)
    try:
        try:
            key = anchor.load_key()
            checkpoint = anchor.read(key)
        except AuditFileError as exc:
            trail.check_order(trail.links[0].n)
            return replace(trail.walk(None)[0], head=f"{exc.path}: {exc.problem}")
        trail.check_order(trail.links[0].n if checkpoint is None else checkpoint.first)
        chain = trail.walk(key)[0]
        if checkpoint is None:
            return replace(chain, head="missing")
        if key is None:
            return replace(chain, head="no-key", checkpoint_rows=checkpoint.rows)
        problem = trail.compare(checkpoint)
    finally:
        trail.close()
    if problem is not None:
        return replace(chain, head=problem, checkpoint_rows=checkpoint.rows)
    last = chain.records if chain.last_row is None else chain.last_row
    return replace(chain, checkpoint_rows=checkpoint.rows,
                   after_checkpoint=max(0, last - checkpoint.rows))  # fmt: skip


def _walk(
    db: sqlite3.Connection, *, prev: str, start: int
) -> tuple[int, int | None, str | None, str]:
    """(records, first broken row, reason, last hash) from recomputing every link of one
    segment, starting from ``prev`` at row ``start``."""
    count, expected_seq = 0, start
    for values in db.execute(_ALL):
        count += 1
        row = dict(zip(_FIELDS, values[:9], strict=True))
        wrong = _wrongly_typed(row)
        if wrong is not None:
            return count, expected_seq, f"invalid {wrong}: a value antireplay never writes", prev
        if row["seq"] != expected_seq:
            return count, expected_seq, "record missing or reordered", prev
        if values[9] != prev:
            return count, row["seq"], "prev_hash does not link", prev
        if values[10] != _digest(prev, row):
            return count, row["seq"], "record contents changed", prev
        prev, expected_seq = values[10], expected_seq + 1
    return count, None, None, prev


def reanchor(
    path: str | PathLike[str],
    *,
    head_key: str | Path | MacKey | None = None,
    head_path: str | Path | None = None,
) -> ChainReport:
    """Accept the current, intact chain as the new head (after an operator checked it),
    from the oldest segment present (older ones missing are accepted as gone; a gap is not).

    Creates a new key when the old one is gone (a damaged or exposed key is replaced,
    never reused) and re-MACs the segment links with it.  Refuses a broken chain."""
    path = Path(path)
    anchor = HeadAnchor(path, head_key,
                        Path(head_path) if head_path else None)  # fmt: skip
    try:
        key = anchor.load_key()
    except AuditFileError:
        key = None
        anchor.key_path.unlink()  # a damaged key is replaced, never reused
    key = key if key is not None else anchor.create_key()
    trail = _Trail(path)
    try:
        trail.check_order(trail.links[0].n)
        chain, head = trail.walk(None)
    finally:
        trail.close()
    if chain.broken_at is not None:
        raise AuditFileError(
            str(path), f"chain broken at row {chain.broken_at}: {chain.reason}; cannot re-anchor",
            recovery=_aside(path),
        )  # fmt: skip
    for file, link in zip(trail.files, trail.links, strict=True):
        if not HeadAnchor.link_ok(key, link):
            segments.relink(file, HeadAnchor.link(key, link.n, link.first, link.prev))
    seq = chain.first_row - 1 + chain.records
    anchor.write(key, seq, head, first=chain.first_segment)
    return replace(chain, checkpoint_rows=seq)


def export_head(
    path: str | PathLike[str],
    file: str | Path,
    *,
    head_key: str | Path | MacKey | None = None,
    head_path: str | Path | None = None,
) -> ChainReport:
    """Write the trail's head checkpoint, MACed with the head key, to ``file`` (for an
    operator to keep elsewhere; ``verify(since=file)`` later proves the trail extends it),
    after :func:`verify` proves it.  Refuses a trail that does not verify."""
    report = verify(path, head_key=head_key, head_path=head_path)
    if not report.ok or report.checkpoint_rows is None:
        raise AuditFileError(str(path), "not exported: " + "; ".join(report.lines()),
                             recovery=f"antireplay audit verify {path}")  # fmt: skip
    anchor = HeadAnchor(Path(path), head_key,
                        Path(head_path) if head_path else None)  # fmt: skip
    key = anchor.load_key()
    checkpoint = anchor.read(key)
    assert key is not None and checkpoint is not None, "verified: both exist"
    consistency.export(anchor, key, checkpoint, Path(file))
    return report
