"""The gateway's read-only status page: ``GET /`` (HTML) and ``GET /status.json`` (the same data).

Theory of operation
-------------------
**Read-only.**  A glance must never change what it looks at: building the page records
nothing (no audit row, no store write, no counter), so it can be reloaded, scraped or left
open without touching the replay state, and an unauthenticated visitor changes nothing
(the first law: nothing an unauthenticated request carries changes state).

**One source of truth each.**  :func:`snapshot` builds one dict and both routes answer
from it: ``/status.json`` is the dict, ``/`` is :func:`render` of it.  The counters are the
samples ``/metrics`` exports, read by collecting the gateway's own Prometheus registry
(:class:`~antireplay.http.metrics.Metrics` and its ``StateCollector``): accepted, rejected by
code, warnings, store and upstream errors, the replay window's refusals by cause (fence and
store failures included), group-commit batches.
Store health is that collector's view of the backend in use (entries, watermark, fence,
data-loss events) plus the reason :func:`antireplay.http.app.readiness` gives (``None``:
ready).  The recent audit records are read by :func:`antireplay.audit.tail` (what
``antireplay audit tail`` runs: a fresh read-only connection, so the writer's lock is not
taken) and shown as :func:`antireplay.audit.shown` shows them.  The audit trail holds no
payload, so none can appear here.  All of it is blocking I/O, run in a worker thread.

**Sanitized, escaped, confined.**  msg_ids, senders and reasons come from attackers.
Audit strings pass ``sanitize`` again (only ``[A-Za-z0-9._:@/-]``, else a hash), and every
value on the page, our own codes, paths and exception texts included, is HTML-escaped
where it is written (:func:`_text`); nothing is ever inserted unescaped.  Should that fail,
the Content-Security-Policy still lets nothing run or load: ``default-src 'none'`` with
the one inline stylesheet allowed by a per-response nonce, no scripts at all, no framing,
no forms; ``nosniff`` and ``no-store`` keep browsers and proxies from reinterpreting or
keeping it.  The page reloads itself every 5 s with ``<meta http-equiv=refresh>``;
``GET /favicon.ico`` answers 204, so a browser's console stays empty (which the Chromium
test checks: a CSP violation would be an error there).
"""

from __future__ import annotations

import html
import math
import secrets
import sqlite3
import time
from collections.abc import Callable, Iterable
from typing import Any

from prometheus_client import CollectorRegistry
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, Response
from starlette.routing import Route

from antireplay.audit import AuditLog, shown, tail
from antireplay.core.errors import StateFileError
from antireplay.rcan.receive import Receiver

#: Audit records shown (the newest first).
RECENT = 20
#: Seconds between the page's own reloads.
REFRESH_S = 5
Readiness = Callable[[Receiver], str | None]
#: The audit columns shown (what ``antireplay audit tail`` prints).
AUDIT_COLUMNS = ("seq", "time", "outcome", "code", "warning", "msg_type", "sender", "msg_id")
_STYLE = """
body{font:14px/1.4 system-ui,sans-serif;margin:1.5em;color:#222;background:#fafafa}
h1{font-size:1.4em;margin:0 0 .3em}
.ready{color:#0a6b2d}.unready{color:#a40000}
section{display:flex;flex-wrap:wrap;gap:1.5em;align-items:flex-start}
table{border-collapse:collapse;background:#fff;margin-bottom:1em}
caption{text-align:left;font-weight:600;padding:.3em 0;white-space:nowrap}
th,td{border:1px solid #ddd;padding:.25em .6em;text-align:left;vertical-align:top}
td{font-family:ui-monospace,monospace;word-break:break-all}
.none{color:#777;font-style:italic}
footer{color:#777;font-size:.9em}
"""
Samples = dict[str, list[tuple[dict[str, str], float]]]


def rolled_back(audit: AuditLog) -> str | None:
    """``AUDIT_ROLLED_BACK: why`` while the trail was found rolled back against the state's
    record of its head, else ``AUDIT_HEAD_BEHIND: why`` while its head checkpoint cannot be
    written (commands are still served: the replay state is intact, every row reaches the
    trail; what lags is the MACed head that vouches for them)."""
    if audit.rolled_back is not None:
        return f"AUDIT_ROLLED_BACK: {audit.rolled_back}"
    return None if audit.head_behind is None else f"AUDIT_HEAD_BEHIND: {audit.head_behind}"


def snapshot(
    receiver: Receiver, registry: CollectorRegistry, readiness: Readiness, records: int = RECENT
) -> dict[str, Any]:
    """Everything the page shows, as plain JSON values (blocking: store, audit file)."""
    samples: Samples = {}
    for metric in registry.collect():
        for sample in metric.samples:
            samples.setdefault(sample.name, []).append((sample.labels, sample.value))
    reason = readiness(receiver)
    rejected = _by(samples, "antireplay_rejected_total", "code")
    entries = samples.get("antireplay_cache_entries", [])
    batches = _by(samples, "antireplay_group_commit_batches_total", "log")
    operations = _by(samples, "antireplay_group_commit_operations_total", "log")
    return {
        "generated_at": time.time(),
        "ready": reason is None,
        "reason": reason,
        "warning": None if receiver.audit is None else rolled_back(receiver.audit),
        "counters": {
            "accepted": _total(samples, "antireplay_accepted_total"),
            "rejected_total": sum(v or 0 for v in rejected.values()),
            "rejected": rejected,
            "warnings": _by(samples, "antireplay_warnings_total", "warning"),
            "store_errors": _total(samples, "antireplay_store_errors_total"),
            "upstream_errors": _total(samples, "antireplay_upstream_errors_total"),
            "replay_refusals": _by(samples, "antireplay_replay_refusals_total", "cause"),
            "restart_fence_rejections": _total(
                samples, "antireplay_restart_fence_rejections_total"
            ),
            "latency_observations": _total(samples, "antireplay_latency_seconds_count"),
        },
        "store": {
            "backend": next((labels.get("backend") for labels, _ in entries), None),
            "entries": _total(samples, "antireplay_cache_entries"),
            "watermark": _total(samples, "antireplay_state_watermark_seconds"),
            "fence": _total(samples, "antireplay_state_fence_seconds"),
            "data_loss_events": _total(samples, "antireplay_state_data_loss_total"),
            "watermark_raises": _total(samples, "antireplay_watermark_raises_total"),
        },
        "group_commit": {
            log: {"batches": n, "operations": operations.get(log)} for log, n in batches.items()
        },
        "audit": _audit(receiver, records),
    }


def _number(value: float) -> float | int | None:
    """A sample as JSON allows it: NaN (the store did not answer) becomes ``None``."""
    if not math.isfinite(value):
        return None
    return int(value) if float(value).is_integer() else value


def _total(samples: Samples, name: str) -> float | int | None:
    values = [v for _, v in samples.get(name, [])]
    return _number(sum(values)) if values else None


def _by(samples: Samples, name: str, label: str) -> dict[str, float | int | None]:
    return {labels[label]: _number(v) for labels, v in samples.get(name, []) if label in labels}


def _audit(receiver: Receiver, records: int) -> dict[str, Any]:
    """The newest records of the gateway's trail, or why they cannot be read (never raises)."""
    if receiver.audit is None:
        return {"path": None, "records": [], "error": "no audit trail configured"}
    path = str(receiver.audit.path)
    try:
        rows = [shown(r) for r in tail(path, records)]
    except StateFileError as exc:  # its wording is for a refused start: this one runs
        error = (
            f"audit trail {path} deleted under the running gateway: every command is refused "
            f"(503); stop the gateway and restore the file, or see `antireplay audit reanchor`"
            if not receiver.audit.path.exists()
            else f"audit file {exc.path}: {exc.problem}. Recover with: {exc.recovery}"
        )
        return {"path": path, "records": [], "error": error}
    except (sqlite3.Error, OSError) as exc:
        return {"path": path, "records": [], "error": str(exc)}
    return {"path": path, "records": rows[::-1], "error": None}


def _text(value: object) -> str:
    """Any value as inert HTML text (``None`` as a dash)."""
    return "\u2014" if value is None else html.escape(str(value), quote=True)


def _when(seconds: object) -> str:
    """A Unix time as ISO 8601 UTC next to its value (0 or unknown: the value alone)."""
    if not isinstance(seconds, int | float) or seconds <= 0:
        return _text(seconds)
    try:
        iso = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(seconds))
    except (OverflowError, OSError, ValueError):  # beyond the platform's calendar
        return _text(seconds)
    return f"{_text(iso)} ({_text(seconds)})"


#: What ``antireplay_replay_refusals_total`` counts: the replay window's refusals (its
#: fence, store failures, stale, replayed msg_id: receive steps 3 and 7), not every
#: ``REPLAY_DETECTED``: a byte-identical copy refused at step 0 (or a QoS retransmission
#: answered again) never reaches the window, and is counted under "Rejected by code" only.
_WINDOW_REFUSALS = (
    "Replay-window refusals by cause (steps 3 and 7, fence and store included; "
    "byte-identical copies count under Rejected by code only)"
)


def _table(caption: str, rows: Iterable[tuple[object, str]]) -> str:
    """A two-column table (id: its caption in kebab case); the second column is HTML the
    caller already escaped."""
    body = "".join(f"<tr><th>{_text(k)}</th><td>{v}</td></tr>" for k, v in rows)
    ident = caption.lower().replace(" ", "-")
    return (
        f'<table id="{_text(ident)}"><caption>{_text(caption)}</caption>'
        f"{body or _empty(2, 'none')}</table>"
    )


def _empty(columns: int, text: str) -> str:
    return f'<tr><td colspan="{columns}" class="none">{_text(text)}</td></tr>'


def render(data: dict[str, Any], nonce: str) -> str:
    """The page for one :func:`snapshot` (every value escaped; no script)."""
    counters, store, audit = data["counters"], data["store"], data["audit"]
    if data["ready"]:
        state = '<p id="readiness" class="ready">ready: store and audit trail answer</p>'
    else:
        state = f'<p id="readiness" class="unready">not ready: {_text(data["reason"])}</p>'
    if data.get("warning"):
        state += f'<p id="warning" class="unready">{_text(data["warning"])}</p>'
    totals = [
        ("accepted", _text(counters["accepted"])),
        ("rejected", _text(counters["rejected_total"])),
        ("store errors", _text(counters["store_errors"])),
        ("upstream errors", _text(counters["upstream_errors"])),
        ("restart fence rejections", _text(counters["restart_fence_rejections"])),
        ("latency observations", _text(counters["latency_observations"])),
    ]
    health = [
        ("backend", _text(store["backend"])),
        ("entries", _text(store["entries"])),
        ("watermark", _when(store["watermark"])),
        ("fence", _when(store["fence"])),
        ("data-loss events", _text(store["data_loss_events"])),
        ("watermark raises", _text(store["watermark_raises"])),
    ]
    commits = [
        (f"{log} batches / records", f"{_text(c['batches'])} / {_text(c['operations'])}")
        for log, c in data["group_commit"].items()
    ]
    head = "".join(f"<th>{_text(c)}</th>" for c in AUDIT_COLUMNS)
    rows = "".join(
        "<tr>" + "".join(f"<td>{_text(_cell(record, c))}</td>" for c in AUDIT_COLUMNS) + "</tr>"
        for record in audit["records"]
    )
    if audit["error"] is not None:
        rows = _empty(len(AUDIT_COLUMNS), f"cannot read the audit trail: {audit['error']}")
    caption = f"Recent audit records (newest first): {audit['path']}"
    return (
        "<!DOCTYPE html>\n"
        '<html lang="en"><head><meta charset="utf-8">'
        f'<meta http-equiv="refresh" content="{REFRESH_S}">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        "<title>antireplay status</title>"
        f'<style nonce="{_text(nonce)}">{_STYLE}</style></head><body>'
        f"<h1>antireplay status</h1>{state}<section>"
        + _table("Counters", totals)
        + _table("Rejected by code", _pairs(counters["rejected"]))
        + _table("Warnings", _pairs(counters["warnings"]))
        + _table(_WINDOW_REFUSALS, _pairs(counters["replay_refusals"]))
        + _table("Store health", health)
        + _table("Group commit", commits)
        + "</section>"
        f'<table id="audit"><caption>{_text(caption)}</caption><tr>{head}</tr>'
        f"{rows or _empty(len(AUDIT_COLUMNS), 'no records yet')}</table>"
        f"<footer>read-only; generated {_when(data['generated_at'])}; the same data as "
        '<a href="status.json">status.json</a>; reloads every '
        f"{REFRESH_S} s</footer></body></html>\n"
    )


def _pairs(counts: dict[str, Any]) -> list[tuple[object, str]]:
    return [(key, _text(value)) for key, value in sorted(counts.items())]


def _cell(record: dict[str, Any], column: str) -> object:
    """One audit cell; an unauthenticated sender is marked as only claimed, as ``audit tail``
    does."""
    if column == "sender" and record["sender"] is not None and not record["sender_verified"]:
        return f"{record['sender']} (claimed)"
    return record[column]


def security_headers(nonce: str | None = None) -> dict[str, str]:
    """The headers of every status response: nothing may run, load or frame it; only the
    page's one stylesheet (``nonce``) applies; never sniffed, cached or referred onward."""
    style = f"'nonce-{nonce}'" if nonce else "'none'"
    policy = (
        f"default-src 'none'; style-src {style}; base-uri 'none'; form-action 'none'; "
        "frame-ancestors 'none'"
    )
    return {
        "Content-Security-Policy": policy,
        "X-Content-Type-Options": "nosniff",
        "Cache-Control": "no-store",
        "Referrer-Policy": "no-referrer",
    }


def routes(receiver: Receiver, registry: CollectorRegistry, readiness: Readiness) -> list[Route]:
    """``GET /``, ``GET /status.json`` and ``GET /favicon.ico`` for the gateway's receiver and
    metrics registry."""

    async def page(_: Request) -> Response:
        data = await run_in_threadpool(snapshot, receiver, registry, readiness)
        nonce = secrets.token_urlsafe(16)
        return HTMLResponse(render(data, nonce), headers=security_headers(nonce))

    async def as_json(_: Request) -> Response:
        data = await run_in_threadpool(snapshot, receiver, registry, readiness)
        return JSONResponse(data, headers=security_headers())

    async def no_icon(_: Request) -> Response:
        """What browsers ask for next to the page: nothing (not a 404 in their console)."""
        return Response(status_code=204, headers=security_headers())

    return [
        Route("/", page, methods=["GET"]),
        Route("/status.json", as_json, methods=["GET"]),
        Route("/favicon.ico", no_icon, methods=["GET"]),
    ]
