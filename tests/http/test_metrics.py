"""The gateway's metrics and its audit trail agree on every refusal, whatever folded it."""

from __future__ import annotations

import json
import re
from pathlib import Path

from antireplay.audit import tail
from antireplay.audit.refusals import SUMMARY, summary_count
from antireplay.cli.demo import command, load_operator_key
from harness.asgi import demo_app, request


def _samples(text: str, name: str) -> float:
    """The sum of every sample of ``name`` in an exposition."""
    found = re.findall(rf"^{re.escape(name)}(?:\{{[^}}]*\}})? ([0-9.e+]+)$", text, re.MULTILINE)
    return sum(float(v) for v in found)


def test_rows_and_summaries_add_up_to_the_rejected_metric_for_mixed_causes_and_senders(
    tmp_path: Path,
) -> None:
    """Replays, stale captures, forgeries under 40 claimed senders and garbage, far beyond
    the row budgets: the rejected counter, and the trail's rows plus its summaries' counts,
    both say exactly how many were refused."""
    with demo_app(tmp_path) as app:
        key = load_operator_key(tmp_path)
        raw = command(key)
        assert request(app, "POST", "/v1/messages", raw).status_code == 200
        stale = command(key, age_s=120)
        sent = 0
        for i in range(400):
            forged = {**json.loads(command(key)), "cmd": "x", "sender": f"claimed-{i % 40}"}
            body = (raw, stale, json.dumps(forged).encode(), b"{")[i % 4]
            assert request(app, "POST", "/v1/messages", body).status_code >= 400
            sent += 1
        text = request(app, "GET", "/metrics").text
        assert _samples(text, "antireplay_rejected_total") == sent
        folded = _samples(text, "antireplay_audit_refusals_folded_total")
        assert folded > sent / 2  # most refusals were folded, not written one by one
        receiver = app.state.receiver
        receiver.close()  # the summaries, as at shutdown
        assert receiver.refusals.summarised == folded and receiver.refusals.unrecorded == 0
    rows = [r for r in tail(tmp_path / "audit.db", 100_000) if r.outcome != "accepted"]
    assert sum(summary_count(r.outcome, r.warning) for r in rows) == sent
    codes = {r.code for r in rows if r.outcome == SUMMARY}
    assert {"REPLAY_DETECTED", "MESSAGE_STALE", "INVALID_ENVELOPE"} <= codes
    assert len(rows) < 150


def test_disk_and_trail_gauges_are_exported(tmp_path: Path) -> None:
    with demo_app(tmp_path) as app:
        assert request(app, "POST", "/v1/messages", command(load_operator_key(tmp_path))).is_success
        text = request(app, "GET", "/metrics").text
        assert _samples(text, "antireplay_audit_free_bytes") > 0
        assert _samples(text, "antireplay_audit_trail_bytes") > 0
        assert _samples(text, "antireplay_audit_trail_segments") == 1
        assert 0 <= _samples(text, "antireplay_audit_oldest_row_age_seconds") < 3600
        assert _samples(text, "antireplay_audit_disk_pressure") == 0
        app.state.receiver.close()
