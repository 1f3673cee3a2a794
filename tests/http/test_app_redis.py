"""End to end: two `antireplay serve` processes sharing one real Redis that loses state.

A Redis that restarts from an older RDB snapshot, or a replica promoted after missing
the last write, has forgotten a message a gateway accepted.  Replaying that message to
either gateway must never be accepted, and the refusal must be visible where an operator
looks: the gateway's /metrics and its audit trail.  Gateways run on the system clock, so
messages are signed with real time; a fence is waited out by polling fresh messages.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx

from antireplay.audit import AuditLog, Record
from antireplay.cli.demo import command, load_operator_key, write_demo_config
from harness import (
    GatewayProcess,
    accepted_fresh,
    data_losses,
    metric,
    post,
    post_after_cut,
    reencoded,
    serving,
)
from harness.redis_server import RedisServer, primary_and_replica, wait_replicated

#: A short skew keeps the fence a fresh deployment (or a loss) raises short.
SKEW_S = 1


@contextmanager
def two_gateways(tmp_path: Path, store: str) -> Iterator[tuple[GatewayProcess, GatewayProcess]]:
    """Gateways A and B on one store, each with its own audit trail, trusting one key."""
    a_dir, b_dir = tmp_path / "a", tmp_path / "b"
    a_dir.mkdir()
    b_dir.mkdir()
    overrides = {"store": store, "security": {"skew_s": SKEW_S}}
    a_config = write_demo_config(a_dir, **overrides)
    b_config = write_demo_config(b_dir, **overrides)
    (b_dir / "operator.pub.pem").write_bytes((a_dir / "operator.pub.pem").read_bytes())
    with serving(a_config) as a, serving(b_config) as b:
        yield a, b


def answer(reply: httpx.Response) -> tuple[int, str | None, str | None]:
    body = reply.json()
    return reply.status_code, body.get("code"), body.get("detail")


def fence_refusals(gateway: GatewayProcess) -> float:
    return metric(gateway, "antireplay_replay_refusals_total", '{cause="restart_fence"}')


def assert_never_accepted(a: GatewayProcess, b: GatewayProcess, captured: bytes) -> None:
    """Every replay of ``captured`` (to B, to A, byte-identical or re-encoded) is refused;
    B (which never saw it) notices the loss on its commit and refuses it by the fence."""
    first = post_after_cut(b, captured)
    assert answer(first) == (408, "MESSAGE_STALE", "restart_fence"), first.text
    for gateway in (b, a):
        for raw in (captured, reencoded(captured)):
            reply = post_after_cut(gateway, raw)
            assert answer(reply) in {
                (408, "MESSAGE_STALE", "restart_fence"),
                (409, "REPLAY_DETECTED", None),
            }, reply.text


def assert_on_the_record(audit: Path, msg_id: str) -> None:
    """The gateway audited the loss (STATE_LOST) and the fenced replay of ``msg_id``."""
    records: list[Record] = AuditLog(audit).tail(1000)
    assert any(r.outcome == "state" and r.code == "STATE_LOST" for r in records), records
    fenced = [r for r in records if r.msg_id == msg_id and r.code == "MESSAGE_STALE"]
    assert fenced and all(r.warning == "restart_fence" for r in fenced), records
    assert not any(r.msg_id == msg_id and r.outcome == "accepted" for r in records), records


def test_redis_restart_from_an_older_snapshot_never_reaccepts(tmp_path: Path) -> None:
    redis_server = RedisServer(tmp_path, snapshots=True)
    redis_server.start()
    try:
        with two_gateways(tmp_path, redis_server.url) as (a, b):
            accepted_fresh(a, tmp_path / "a")  # the first contact fences for SKEW_S seconds
            accepted_fresh(b, tmp_path / "a")
            redis_server.save()  # the snapshot holds the deployment, not what follows
            captured = command(load_operator_key(tmp_path / "a"))
            assert post(a, captured).status_code == 200
            losses_before = data_losses(b)
            redis_server.kill()
            redis_server.start()  # loads dump.rdb: the captured message is gone
            assert_never_accepted(a, b, captured)
            assert fence_refusals(b) >= 1
            assert data_losses(b) == losses_before + 1
            accepted_fresh(a, tmp_path / "a")  # and service resumes once the fence passed
        msg_id = json.loads(captured)["msg_id"]
        assert_on_the_record(tmp_path / "b" / "audit.db", msg_id)
        a_records = AuditLog(tmp_path / "a" / "audit.db").tail(1000)
        assert [r.outcome for r in a_records if r.msg_id == msg_id].count("accepted") == 1
    finally:
        redis_server.stop()


def test_promoted_replica_that_missed_the_last_write_never_reaccepts(tmp_path: Path) -> None:
    with primary_and_replica(tmp_path) as (primary, replica, vip):
        with two_gateways(tmp_path, vip.url) as (a, b):
            accepted_fresh(a, tmp_path / "a")
            accepted_fresh(b, tmp_path / "a")
            wait_replicated(primary, replica)
            replica.client().replicaof("no", "one")  # the link breaks: the replica misses ...
            captured = command(load_operator_key(tmp_path / "a"))
            assert post(a, captured).status_code == 200  # ... this write
            losses_before = data_losses(b)
            primary.kill()
            vip.point_to(replica.port)  # failover behind the same address
            assert_never_accepted(a, b, captured)
            assert fence_refusals(b) >= 1
            assert data_losses(b) == losses_before + 1
            accepted_fresh(b, tmp_path / "a")
        assert_on_the_record(tmp_path / "b" / "audit.db", json.loads(captured)["msg_id"])
