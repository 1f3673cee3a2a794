"""The audit trail: append-only, hash-chained records in SQLite; never the payload.

Theory of operation
-------------------
Every accepted message and every rejection that matters is one row:
time, outcome, code, warning, message type, sender (the authenticated owner,
or the claimed ``sender`` marked unverified) and a sanitized msg_id.  Attacker
strings are never stored raw: an identifier is kept only if it is at most 64
characters of ``[A-Za-z0-9._:@/-]``; anything else is replaced by
``sha256:<first 16 hex>`` of it, so no log line can be forged with newlines,
escapes or terminal codes, and nothing from ``params`` is ever written.

Each row stores ``hash = SHA-256(prev_hash | canonical JSON of the row)``; the
first row chains from 64 zeros.  :func:`verify` recomputes the chain and
reports the first broken link, so an edited, deleted or reordered row is
detected.  Writes use WAL with ``synchronous=FULL``: ``append`` returns after
the record is durable, so a crash never loses a committed record.  Appends are
**group-committed** (:mod:`antireplay.state.groupcommit`): the rows of concurrent
callers are chained and committed in one transaction with one fsync and one
head checkpoint, each caller answered once its own row is durable, so a replay
flood costs one fsync per batch of rejections, not one each.

**The head is anchored outside the database.**  The chain alone cannot show
that its newest rows were deleted, and whoever can write the database can
recompute a whole new chain.  So, like a transparency log's signed tree head,
the head ``(rows, last hash)`` is MACed (HMAC-SHA256) with a key that is not in
the database and checkpointed to a file outside it (:class:`HeadAnchor`):
``PATH.key`` (32 random bytes as hex, mode 0600, created on first use; or a
configured path, ideally somewhere the database's writers cannot read) and
``PATH.head``, one fixed-size record).  The checkpoint names the last row and
is rewritten in place after every commit batch, so it survives a ``kill -9``
at once (the page cache outlives the process), but it is ``fdatasync``-ed at
most once every ``head_sync_s`` (and on close), not once per batch: a head
that lags only *under*-claims.  Why that is sound: the checkpoint is the
floor a truncation or rewrite is judged against, and every checkpoint ever
written names a genuine row of the chain.  After a power cut an older (still
genuine, MAC-verified) checkpoint may come back; every row it names is still
proven, and the rows after it (at most ``head_sync_s`` of appends, like a
crash between a commit and its checkpoint before) are counted and reported
as not covered, never passed off as proven.  A rollback of the database below
the checkpoint on disk is refused exactly as before.  The in-place write of
one 256-byte record sits inside one disk sector, so a power cut leaves the old
record or the new one; anything else reads as corrupt and refuses (fails
closed).  ``verify`` then proves: the chain links up to row N; the
checkpoint's MAC is genuine and row ``rows`` still has the checkpointed hash
(no truncation, no rewrite without the key); rows after the checkpoint (a
power cut within ``head_sync_s``, or rows appended by someone without the
key) are counted and reported as not covered.  It cannot prove anything against someone who holds
the key, nor against a rollback of the database *and* the head file together
to an older genuine pair (publish the head elsewhere for that).

**Refuse, never guess.**  Opening a file that is not an SQLite database, an
SQLite database that is not an audit trail, a database truncated or rewritten
since its checkpoint, a deleted checkpoint or key, or a damaged key raises
:class:`~antireplay.core.errors.AuditFileError`, which names the file and the
recovery (``antireplay audit verify PATH`` to see what is provable, then
``antireplay audit reanchor PATH`` to accept the current chain as the new
head, or moving the files aside to start a new trail).  Only an *empty* trail
is anchored automatically; a trail with rows and neither key nor checkpoint
(made before anchoring existed, or both files deleted) waits for an operator's
``antireplay audit reanchor PATH``.  A trail deleted while its checkpoint stays is
refused by name before any file is created (a refused start leaves nothing behind); a
running writer checks, before each group commit, that its path still names the file it
opened, so rows are never appended to a deleted (or replaced) trail where they would be
lost: those appends fail (``STATE_UNAVAILABLE``) instead.

Refusals reach the trail through one rate-limited :class:`RefusalAuditor`
(:mod:`antireplay.audit.refusals`); accepted messages always get their own row.
"""

from antireplay.audit.chain import GENESIS, Checkpoint, HeadAnchor, Record, sanitize
from antireplay.audit.reader import shown, tail
from antireplay.audit.refusals import RefusalAuditor
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
    "reanchor",
    "sanitize",
    "shown",
    "tail",
    "verify",
]
