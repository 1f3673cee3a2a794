"""Reading an audit trail: the newest records (across its segments), and what an operator
is shown of one."""

from __future__ import annotations

import time
from os import PathLike
from pathlib import Path
from typing import Any

from antireplay.audit.chain import (
    Record,
    printable,
    sanitize,
    valid_at,
)
from antireplay.audit.segments import newest


def tail(path: str | PathLike[str], n: int = 20) -> list[Record]:
    """The newest ``n`` records across segments, read-only: reading never writes a
    checkpoint or a key."""
    return newest(Path(path), n)


def shown(record: Record) -> dict[str, Any]:
    """One record as ``audit tail`` and the status page show it, whatever a trail edited
    behind our back holds: identifiers through ``sanitize`` again, the warning (a STATE_LOST
    reason is free text) through ``printable``, numbers only if they are numbers antireplay
    writes (else ``sanitize``d, and an impossible time is ``null`` / "invalid"), the time
    also as ISO 8601 UTC."""
    at = valid_at(record.at)
    return {
        "seq": record.seq if type(record.seq) is int else sanitize(record.seq),
        "at": at,
        "time": "invalid" if at is None else time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(at)),
        "outcome": sanitize(record.outcome),
        "code": sanitize(record.code),
        "warning": printable(record.warning),
        "msg_type": record.msg_type if type(record.msg_type) is int else sanitize(record.msg_type),
        "sender": sanitize(record.sender),
        "sender_verified": record.sender_verified,
        "msg_id": sanitize(record.msg_id),
    }
