"""The audit trail: append-only, hash-chained records in SQLite; never the payload.

Theory of operation
-------------------
Every accepted message and every refusal that matters is one row: time, outcome,
code, warning, message type, sender (the authenticated owner, or the claimed one
marked unverified) and a sanitized msg_id (at most 64 characters of
``[A-Za-z0-9._:@/-]``, else ``sha256:<16 hex>``), so no row can forge a log line and
nothing from ``params`` is written.  Refusals pass through one rate-limited
:class:`RefusalAuditor` (a budget for authenticated refusals, one for the rest);
accepted messages always get their own row.

Each row stores ``hash = SHA-256(prev_hash | canonical JSON of the row)``
(:mod:`.chain`).  The writer (:class:`AuditLog`) group-commits: concurrent rows are
chained and made durable in one transaction and one fsync, each caller answered
once its own row is durable.  The head ``(rows, last hash)`` is MACed with a key
kept outside the database and checkpointed to ``PATH.head`` after every batch
(fsynced at most every ``head_sync_s``; an older genuine checkpoint only
under-claims), like a transparency log's signed head: :func:`verify` proves the
chain, the checkpoint's MAC and that no checkpointed row was truncated or
rewritten, and counts the rows after it as not covered.  It proves nothing against
a holder of the key, nor a rollback of the database and the head file together.

The trail is a sequence of segments (:mod:`.segments`): ``PATH`` is the live one,
rotated ones are ``PATH.000041``, each chained from the one before by a MACed link;
retention removes the oldest whole segments only, and :func:`verify` says where it cut.

Refuse, never guess: a file that is not an audit trail, a trail truncated or
rewritten since its checkpoint, a missing checkpoint or key raise
:class:`~antireplay.core.errors.AuditFileError` naming the file and the recovery
(``antireplay audit verify`` / ``reanchor``); appends to a trail deleted under a
running writer fail with ``STATE_UNAVAILABLE``.
"""

from antireplay.audit.chain import GENESIS, Checkpoint, HeadAnchor, Record, sanitize
from antireplay.audit.reader import shown, tail
from antireplay.audit.refusals import RefusalAuditor
from antireplay.audit.segments import Retention, TrailUsage
from antireplay.audit.verifier import ChainReport, reanchor, verify
from antireplay.audit.writer import AuditLog

__all__ = [
    "GENESIS",
    "AuditLog",
    "ChainReport",
    "Checkpoint",
    "HeadAnchor",
    "Record",
    "RefusalAuditor",
    "Retention",
    "TrailUsage",
    "reanchor",
    "sanitize",
    "shown",
    "tail",
    "verify",
]
