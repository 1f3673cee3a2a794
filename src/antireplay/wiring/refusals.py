"""Refused MAVLink frames on the record: one rate-limited auditor for the router and the PQ ends.

Theory of operation
-------------------
:func:`mavlink_auditor` is the ``on_reject`` of the router and of each post-quantum end: a
dropped frame becomes an audit row and a log line with its direction and the source its
header claims (``mav:inbound:255/190``, unverified) through the one rate-limited
:class:`~antireplay.audit.RefusalAuditor`; what it folds is counted (a metric).  Below the
first free-space floor under the trail (``audit_space.min_free_bytes``) it goes quiet:
refusals are counted, not written, as the gateway's are.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from antireplay.audit import AuditLog, RefusalAuditor
from antireplay.core.clock import Clock

if TYPE_CHECKING:
    from antireplay.mavlink import FrameRefusal

#: Audit records and log lines per second for refused MAVLink frames (the rest are counted).
MAVLINK_AUDIT_PER_S = 50.0
log = logging.getLogger("antireplay.mavlink")


def mavlink_auditor(
    audit: AuditLog, clock: Clock | None = None, *, quiet: Callable[[], bool] | None = None
) -> MavlinkRefusals:
    """The router's (or a PQ end's) ``on_reject``: an audit row and a log line per dropped
    frame, through the rate-limited :class:`~antireplay.audit.RefusalAuditor`; ``quiet``
    (the trail's free space below its first floor) turns rows into counts."""
    return MavlinkRefusals(
        RefusalAuditor(audit, clock, per_s=MAVLINK_AUDIT_PER_S, log=log, quiet=quiet)
    )


@dataclass(frozen=True)
class MavlinkRefusals:
    """A dropped frame on the record: its direction and the source its header claims
    (``mav:inbound:255/190``, unverified).  The router cannot tell which refusals followed
    a verified signature, so every frame spends the unauthenticated budget."""

    auditor: RefusalAuditor

    def close(self) -> None:
        """Write the folded refusals' summary rows (before the trail closes)."""
        self.auditor.close()

    def __call__(self, refusal: FrameRefusal) -> None:
        from antireplay.mavlink import claimed_source  # noqa: PLC0415 - the dialect loads on use

        if refusal.folded:  # behind a restart fence: its link's summary line says it
            return

        source = claimed_source(refusal.raw)
        claimed = "" if source is None else f":{source[0]}/{source[1]}"
        self.auditor.record(
            code=refusal.code, sender=f"mav:{refusal.direction}{claimed}",
            sender_verified=False, line=str(refusal),
        )  # fmt: skip
