"""Consistency: does the trail extend a head recorded elsewhere?  A rolled-back trail is caught.

Theory of operation
-------------------
The head checkpoint lives beside the trail: whoever restores an old copy of the trail
restores its checkpoint too, and the old chain verifies.  So the head is kept in two more
places, each MACed with the head key: the SQLite state database records it with every
drain (:mod:`antireplay.state.outbox`, checked when the writer attaches and by ``audit
verify --state``), and ``audit head --export`` writes it to a file an operator keeps
elsewhere (checked by ``audit verify --since``), as a Certificate Transparency monitor keeps
an old signed tree head.  :func:`extends` proves the trail holds that head's row with
that hash: then every row up to it is the one the head named (the chain links them), and
the trail can only have grown since.  It fails on a trail that ends before that row
(rolled back, truncated) or holds another hash there (rewritten, or rolled back and
written on).  Retention removes whole old segments: a head whose row was in a segment
removed since cannot be compared; what is then proven is that the trail's oldest kept
segment starts, by a link MACed with the key, after that row (a cut made by a key holder,
with every row since chained), not that the removed rows were the ones the head named.
"""

from __future__ import annotations

import sqlite3
from dataclasses import dataclass
from pathlib import Path

from antireplay.audit import segments
from antireplay.audit.chain import Checkpoint, HeadAnchor, HeadKey, _connect, _last, _link
from antireplay.state.outbox import TrailHead

__all__ = ["ROLLED_BACK", "Consistency", "TrailHead", "extends"]

#: The code of a trail found behind (or beside) a head recorded elsewhere.
ROLLED_BACK = "AUDIT_ROLLED_BACK"


@dataclass(frozen=True)
class Consistency:
    """What comparing the trail with a recorded head proved: ``problem`` (a rollback,
    truncation or rewrite, or a head that does not verify) or ``cut`` (the head's row was
    removed by retention: not comparable), neither when the trail extends it."""

    head: Checkpoint
    problem: str | None = None
    cut: str | None = None

    @property
    def ok(self) -> bool:
        return self.problem is None


def recorded(head: TrailHead, key: HeadKey) -> Checkpoint | None:
    """The state's record as a checkpoint if its MAC verifies under ``key``, else ``None``."""
    rows, digest, first, mac = head
    if not HeadAnchor.mac_ok(key, Checkpoint(rows, digest, first), mac):
        return None
    return Checkpoint(rows, digest, first)


def extends(path: Path, live: sqlite3.Connection, head: Checkpoint) -> Consistency:
    """Whether the trail at ``path`` (its live segment open as ``live``) holds ``head``."""
    end, _ = _last(live)
    if head.rows > end:
        return Consistency(head, problem=f"rolled back: row {head.rows} (hash {head.hash[:16]}…) "
                           f"was recorded, the trail ends at row {end}")  # fmt: skip
    found = segments.rotated(path)
    oldest = _first_row(found[0][1]) if found else _link(live).first
    if head.rows < oldest - 1:
        return Consistency(head, cut=(
            f"row {head.rows} was removed by retention (the oldest row kept is {oldest}): "
            f"proven only that the trail was cut by the key's holder after it and chains "
            f"from there; not that the rows removed were the ones recorded"
        ))  # fmt: skip
    problem = segments.compare(path, live, head)
    if problem is not None and problem.startswith("rewritten"):
        problem = f"rolled back or rewritten: row {head.rows} holds another hash than recorded"
    return Consistency(head, problem=problem)


def _first_row(file: Path) -> int:
    db = _connect(file, read_only=True)
    try:
        return _link(db).first
    finally:
        db.close()


def against_state(path: Path, live: sqlite3.Connection, head: TrailHead | None,
                  key: HeadKey) -> Consistency | None:  # fmt: skip
    """The trail against the state database's record (``None``: nothing recorded yet)."""
    if head is None:
        return None
    checkpoint = recorded(head, key)
    if checkpoint is None:
        return Consistency(Checkpoint(head[0], head[1], head[2]), problem=(
            f"replaced: the state database records row {head[0]} of a trail whose head "
            "MAC does not verify under this trail's key (the trail, its head and key "
            "replaced by another)"
        ))  # fmt: skip
    return extends(path, live, checkpoint)


def read_export(file: Path, key: HeadKey | None, trail: Path) -> Checkpoint | None:
    """An exported head (``audit head --export``), MAC-checked under ``key``."""
    return HeadAnchor(trail, head_path=file).read(key)


def export(anchor: HeadAnchor, key: HeadKey, head: Checkpoint, file: Path) -> None:
    """Write ``head`` (a verified checkpoint) to ``file`` for an operator to keep elsewhere."""
    HeadAnchor(anchor.db, anchor.key_path, file).write(key, head.rows, head.hash,
                                                       first=head.first)  # fmt: skip
