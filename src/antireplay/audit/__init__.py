"""The audit trail: append-only, hash-chained records in SQLite; never the payload.

Theory of operation
-------------------
Every accepted message is one row (time, outcome, code, warning, type, sender, a sanitized
msg_id; nothing from ``params``), so no row can forge a log line.  Refusals pass through
one :class:`RefusalAuditor` (:mod:`.refusals`): a bounded rate of them get rows, per class
(authenticated or not) and per sender, and the rest are folded into **summary** rows
("N further REPLAY_DETECTED from Y between t1 and t2"), so a flood is fully counted at
bounded rows per second.  Each row stores ``hash = SHA-256(prev_hash | row)``
(:mod:`.chain`); :class:`AuditLog` group-commits (one transaction and fsync per batch) and
checkpoints the MACed head ``(rows, last hash)`` to ``PATH.head`` under a key kept
outside the trail, so :func:`verify` proves the chain and that no checkpointed row was
truncated or rewritten (not against a holder of the key).

The trail is a sequence of **segments** (:mod:`.segments`): ``PATH`` is the live one,
rotated by size or age to ``PATH.000041``, each chained from the one before by a MACed
link.  **Retention** (``max_bytes``, ``max_age_s``) removes the oldest whole segments
only, recording the cut in the head first: :func:`verify` says where it cut, and a
missing recent segment is tampering.  **Disk floors** (:mod:`.space`): below the first,
refusals are only counted; below the second, new commands are refused with
``STATE_UNAVAILABLE`` and ``/readyz`` says why.  A fresh authentic ESTOP is delivered
through any audit failure; its row goes to the reserved **spill** (:mod:`.spill`) and is
merged into the trail, chained, with the next batch it takes.  A file that is not a
trail, or was rewritten, raises :class:`~antireplay.core.errors.AuditFileError` naming
the recovery (``antireplay audit verify`` / ``reanchor``).  The head is also kept in the
state database and in exports an operator keeps (:mod:`.consistency`): a trail rolled back
against them is ``AUDIT_ROLLED_BACK``.
"""

from antireplay.audit.chain import GENESIS, AuditRow, Checkpoint, HeadAnchor, Record, sanitize
from antireplay.audit.reader import shown, tail
from antireplay.audit.refusals import RefusalAuditor
from antireplay.audit.segments import Retention, TrailUsage
from antireplay.audit.verifier import ChainReport, export_head, reanchor, verify
from antireplay.audit.writer import AuditLog

__all__ = [
    "GENESIS",
    "AuditLog",
    "AuditRow",
    "ChainReport",
    "Checkpoint",
    "HeadAnchor",
    "Record",
    "RefusalAuditor",
    "Retention",
    "TrailUsage",
    "export_head",
    "reanchor",
    "sanitize",
    "shown",
    "tail",
    "verify",
]
