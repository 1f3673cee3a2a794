"""Readiness: whether a guarded receiver can serve commands now, and the endpoint that says so.

``GET /readyz`` answers 200 ``{"status": "ready"}`` when the replay store could take a commit
and the audit trail an append now, free space under the trail is above its second floor, and
the store's fence (a start with no history, a loss it noticed) no longer lies ahead; else 503
with the reason, since every command would be refused too (``fenced until T``: a fresh ESTOP
still passes).  A trail found behind the state's record of it adds a ``warning``
(``AUDIT_ROLLED_BACK``) without failing readiness: the replay state is intact; so does
a head checkpoint that cannot be written (``AUDIT_HEAD_BEHIND``: a failing head key
token).  The probes record nothing (the store's ``ready()``: a read, a write lock taken
and released; the same lock on the audit file), so a probe never notices a loss in place
of the commit that fences and audits it.  The gateway serves :func:`ready_endpoint` at
``/readyz``; an app that embeds the guard mounts the same endpoint
(``GuardBase.ready_endpoint``).
"""

from __future__ import annotations

import sqlite3
from collections.abc import Awaitable, Callable
from datetime import datetime, timezone

from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import JSONResponse, Response

from antireplay.audit import AuditLog
from antireplay.http.status import rolled_back
from antireplay.rcan.receive import Receiver


def ready_endpoint(receiver: Receiver) -> Callable[[Request], Awaitable[Response]]:
    """A Starlette endpoint answering readiness for ``receiver`` (503 with the reason)."""

    async def readyz(_: Request) -> Response:
        reason = await run_in_threadpool(readiness, receiver)
        if reason is not None:
            return JSONResponse({"status": "unavailable", "reason": reason}, status_code=503)
        warning = None if receiver.audit is None else rolled_back(receiver.audit)
        return JSONResponse({"status": "ready", **({"warning": warning} if warning else {})})

    return readyz


def readiness(receiver: Receiver) -> str | None:
    """Why the gateway cannot serve commands now (store or audit trail), ``None`` if it can.

    Blocking I/O (run it in a thread); records nothing."""
    try:
        receiver.cache.store.ready()
    except Exception as exc:  # any backend's failure is the reason, never a 500
        return f"store: {exc}"
    fenced = fence_notice(receiver)
    if fenced is not None:
        return fenced
    disk = None if receiver.space is None else receiver.space.reason()
    if disk is not None:
        return disk
    return None if receiver.audit is None else audit_problem(receiver.audit)


def fence_notice(receiver: Receiver) -> str | None:
    """While the store's fence lies ahead (its start with no history, a loss it noticed),
    every command stamped now is refused as ``restart_fence``: say until when, and why
    (``None`` once a command stamped now passes; a fresh ESTOP passes throughout)."""
    cache = receiver.cache
    until = cache.store.fence() + cache.policy.skew_s
    if receiver.clock.wall() > until:
        return None
    when = datetime.fromtimestamp(until, timezone.utc).isoformat(timespec="milliseconds")
    why = getattr(cache.store, "loss_reason", None) or "the store's start (no history)"
    return f"fenced until {when} ({until:.3f}): {why}; a fresh ESTOP still passes"


def audit_problem(audit: AuditLog, timeout_s: float = 1.0) -> str | None:
    """Why ``audit`` could not take an append now, or ``None``: its file is still there and
    its write lock can be taken within ``timeout_s`` (taken and released, nothing written),
    and its head checkpoint file is writable."""
    try:
        db = sqlite3.connect(f"file:{audit.path}?mode=rw", uri=True, timeout=timeout_s)
        try:
            db.execute("BEGIN IMMEDIATE")
            db.execute("ROLLBACK")
        finally:
            db.close()
    except sqlite3.Error as exc:
        return f"audit {audit.path}: {exc}"
    try:
        with audit.anchor.path.open("r+b"):
            pass
    except OSError as exc:
        return f"audit head {audit.anchor.path}: {exc.strerror or exc}"
    return None
