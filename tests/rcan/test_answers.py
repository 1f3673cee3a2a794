"""Safe retries (QoS): a retransmission of an accepted message gets the original answer,
marked duplicate, audited and counted, and never runs twice; an upstream failure is a 502
COMMAND_NACK whose retransmission gets the same 502, never a second upstream call."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from click.testing import CliRunner
from rcan import RCANMessage, RCANResponse
from rcan.exceptions import QoSAckTimeoutError
from rcan.qos import QoSManager
from rcan.signing import MLDSAKeyPair, sign_message

from antireplay import ManualClock, SecurityConfig
from antireplay.audit import AuditLog, verify
from antireplay.cli import main
from antireplay.core.errors import UpstreamFailedError
from antireplay.rcan.answers import MAX_BODY, MAX_TOTAL, AnswerMemo, Entry, HeldAnswer, marked
from antireplay.rcan.auth import JwtVerifier, Signer
from antireplay.rcan.envelope import parse
from antireplay.rcan.receive import Outcome, Receiver
from antireplay.state.loss import NO_HISTORY
from harness import GatewayProcess, free_port, fresh_receiver
from harness.envelopes import (
    ED,
    JWT_KEY,
    NOW,
    PQ,
    message,
    registry,
    sdk_message,
    sdk_registry,
    signed,
    token,
)

ROBOT = "rcan://registry.rcan.dev/acme/arm/v2/unit-001"
JSON = {"content-type": "application/json"}
JSON_HEADERS = (("content-type", "application/json"),)


def answered(
    receiver: Receiver,
    raw: bytes,
    result: object = "moved",
    headers: dict[str, str] | None = None,
) -> Outcome:
    """Receive ``raw`` and, if accepted, hold the answer a transport would have sent."""
    outcome = receiver.receive(raw, headers)
    if outcome.accepted:
        body = json.dumps({**(outcome.ack or {}), "result": result}).encode()
        receiver.hold_answer(outcome, 200, JSON_HEADERS, body)
    return outcome


def last_audit(receiver: Receiver) -> Any:
    assert receiver.audit is not None
    return receiver.audit.tail(1)[0]


# --- the Receiver --------------------------------------------------------------------------


def test_a_qos_retransmission_gets_the_original_answer_marked_audited_counted(
    receiver: Receiver,
) -> None:
    raw = signed(qos=1)
    first = answered(receiver, raw)
    assert first.accepted
    checks = receiver.keys.verifications
    again = receiver.receive(raw)
    assert not again.accepted and again.retry is not None
    assert (again.status, again.code, again.retry.status) == (409, "REPLAY_DETECTED", 200)
    body = json.loads(again.retry.body)
    assert body == {**(first.ack or {}), "result": "moved", "duplicate": True}
    assert ("rcan-duplicate", "true") in again.retry.headers
    assert receiver.keys.verifications == checks  # no crypto for a retransmission
    assert receiver.stats.retries == 1
    row = last_audit(receiver)
    assert (row.outcome, row.code, row.warning) == ("rejected", "REPLAY_DETECTED", "QOS_RETRY")
    assert (row.sender, row.sender_verified, row.msg_id) == ("operator", True, first.msg_id)
    assert receiver.receive(raw).retry == again.retry  # every retransmission, same answer
    assert receiver.stats.accepted == 1


def test_without_qos_a_copy_is_refused_as_before(receiver: Receiver) -> None:
    raw = signed()
    assert answered(receiver, raw).accepted
    again = receiver.receive(raw)
    assert (again.accepted, again.status, again.code, again.retry) == (
        False, 409, "REPLAY_DETECTED", None,
    )  # fmt: skip
    assert last_audit(receiver).warning is None


def test_other_content_under_the_same_msg_id_is_refused(receiver: Receiver) -> None:
    original = message(qos=1)
    assert answered(receiver, signed(**original)).accepted
    msg_id = original["msg_id"]
    checks = receiver.keys.verifications
    other_params = signed(**{**original, "params": {"distance_m": 9.0}})
    other_key = signed("op-pq", PQ, "ml-dsa-65", **original)
    tampered = json.loads(signed(**original))
    tampered["params"] = {"distance_m": 9.0}  # the signature no longer covers it
    no_qos = signed(**{**original, "qos": 0})
    for raw in (other_params, other_key, json.dumps(tampered).encode(), no_qos):
        outcome = receiver.receive(raw)
        assert (outcome.status, outcome.code, outcome.retry) == (409, "REPLAY_DETECTED", None)
        assert outcome.msg_id == msg_id
    assert receiver.keys.verifications == checks  # all refused before any crypto
    assert "original answer not held here" in (receiver.receive(other_params).reason or "")


def test_a_retransmission_past_its_window_is_stale(receiver: Receiver, clock: ManualClock) -> None:
    raw = signed(qos=1)
    assert answered(receiver, raw).accepted
    clock.advance(receiver.config.replay_window_s + receiver.config.skew_s + 1)
    late = receiver.receive(raw)
    assert (late.status, late.code, late.retry) == (408, "MESSAGE_STALE", None)


def test_an_answer_not_held_here_means_409(tmp_path: Path, clock: ManualClock) -> None:
    """Evicted, too large, never handed over, or another receiver on the same store."""
    receiver = fresh_receiver(SecurityConfig(), registry(), None, None, clock)
    receiver.answers = AnswerMemo(1)
    evicted = signed(qos=1)
    assert answered(receiver, evicted).accepted
    assert answered(receiver, signed(qos=1)).accepted  # the memo holds one: evicts the first
    large = signed(qos=1)
    assert answered(receiver, large, result="x" * MAX_BODY).accepted
    unanswered = signed(qos=1)
    assert receiver.receive(unanswered).accepted  # accepted, but no answer handed over yet
    for raw in (evicted, large, unanswered):
        outcome = receiver.receive(raw)
        assert (outcome.status, outcome.code, outcome.retry) == (409, "REPLAY_DETECTED", None)
    assert "still in flight" in (receiver.receive(unanswered).reason or "")
    shared = fresh_receiver(SecurityConfig(), registry(), receiver.cache.store, None, clock)
    raw = signed(qos=1)
    assert answered(receiver, raw).accepted
    assert answered(shared, raw).code == "REPLAY_DETECTED"  # another replica: 409
    assert receiver.stats.retries == 0


def test_an_sdk_signed_retransmission_gets_the_original_answer(clock: ManualClock) -> None:
    """The SDK's qos is unsigned: the digest covers what its signature covers."""
    raw, pair = sdk_message(qos=1)
    receiver = fresh_receiver(SecurityConfig(), sdk_registry(pair, True), None, None, clock)
    first = answered(receiver, raw)
    assert first.accepted and first.envelope is not None and first.envelope.qos == 0
    again = receiver.receive(raw)
    assert again.retry is not None and json.loads(again.retry.body)["duplicate"] is True
    body = json.loads(raw)
    body["params"] = {"distance_m": 5.0}  # outside what was verified
    assert receiver.receive(json.dumps(body).encode()).retry is None


def test_estop_is_unchanged_a_fresh_duplicate_is_processed(receiver: Receiver) -> None:
    raw = signed(cmd="ESTOP", qos=2)
    assert answered(receiver, raw).accepted
    again = receiver.receive(raw)
    assert (again.accepted, again.warning, again.retry) == (True, "REPLAY_DETECTED", None)


def test_a_retransmission_without_the_required_bearer_token_gets_the_originals_refusal(
    tmp_path: Path, clock: ManualClock
) -> None:
    """The held answer carries content (the upstream's result): it goes only to a request
    that passed the authentication an original needs, the token before anything is answered."""
    verifier = JwtVerifier(
        {"jwt-1": JWT_KEY.public_key()}, audience="robot-1", issuer="fleet", clock=clock
    )
    receiver = fresh_receiver(
        SecurityConfig(), registry(), None, AuditLog(tmp_path / "audit.db"), clock,
        jwt=verifier, jwt_required=True,
    )  # fmt: skip
    raw = signed(qos=1)
    bearer = {"Authorization": f"Bearer {token()}"}
    assert answered(receiver, raw, result="secret", headers=bearer).accepted
    original_without_token = receiver.receive(signed(qos=1))
    assert (original_without_token.status, original_without_token.code) == (401, "AUTH_FAILED")
    forged = {"Authorization": f"Bearer {token(sub='intruder')}"}
    on_loop = asyncio.run(receive_on_loop(receiver, raw))
    for refused in (receiver.receive(raw), receiver.receive(raw, forged), on_loop):
        assert (refused.status, refused.code, refused.retry) == (401, "AUTH_FAILED", None)
        assert refused.nack is not None and "secret" not in json.dumps(refused.nack)
    assert receiver.receive(raw).reason == original_without_token.reason
    assert last_audit(receiver).code == "AUTH_FAILED"
    assert receiver.stats.retries == 0
    again = receiver.receive(raw, bearer)  # the same token an original needs: the answer
    assert again.retry is not None and json.loads(again.retry.body)["result"] == "secret"
    assert receiver.stats.retries == 1


async def inline(fn: Callable[..., Any], *args: Any) -> Any:
    """An offload that runs on the loop: the test decides every interleaving."""
    return fn(*args)


async def receive_on_loop(receiver: Receiver, raw: bytes) -> Outcome:
    pending = await receiver.receive_later_async(raw, None, inline)
    if pending.audit is not None:
        await pending.audit  # type: ignore[misc]
    return receiver.settle(pending, None)


async def until_waiting(receiver: Receiver, raw: bytes) -> None:
    """Yield to the loop until a retransmission of ``raw`` waits for the original's answer."""
    entry = receiver.answers.find(parse(raw), NOW)
    assert entry is not None
    for _ in range(1000):
        if entry.waiters:
            return
        await asyncio.sleep(0)
    pytest.fail("the retransmission never waited for the original's answer")


def test_a_retransmission_in_flight_waits_for_the_original_answer(receiver: Receiver) -> None:
    raw = signed(qos=1)

    async def scenario() -> tuple[Outcome, Outcome]:
        first = await receive_on_loop(receiver, raw)
        assert first.accepted  # answer not handed over yet: in flight
        retry = asyncio.ensure_future(receive_on_loop(receiver, raw))
        await until_waiting(receiver, raw)
        assert not retry.done()
        receiver.hold_answer(first, 201, JSON_HEADERS, json.dumps(first.ack).encode())
        return first, await retry

    first, again = asyncio.run(scenario())
    assert again.retry is not None and again.retry.status == 201
    assert json.loads(again.retry.body) == {**(first.ack or {}), "duplicate": True}


def test_a_retransmission_in_flight_gets_409_when_no_answer_comes(receiver: Receiver) -> None:
    raw = signed(qos=1)
    receiver.answer_wait_s = 0

    async def scenario() -> Outcome:
        assert (await receive_on_loop(receiver, raw)).accepted
        return await receive_on_loop(receiver, raw)

    late = asyncio.run(scenario())
    assert (late.status, late.code, late.retry) == (409, "REPLAY_DETECTED", None)
    assert "none arrived in time" in (late.reason or "")


def test_two_copies_racing_through_crypto_the_loser_gets_the_winner_s_answer(
    receiver: Receiver,
) -> None:
    """Both pass the check before either commits (step 7 refuses the loser): the loser is
    as authentic as the winner, and waits for the winner's answer."""
    raw = signed(qos=1)
    receiver.answer_wait_s = 60  # only the winner's answer ends the wait in this test
    gate = asyncio.Event()
    at_gate: list[str] = []

    async def gated(fn: Callable[..., Any], *args: Any) -> Any:
        if getattr(fn, "__name__", "") == "commit":
            at_gate.append("commit")
            await gate.wait()
        return fn(*args)

    async def one() -> Outcome:
        pending = await receiver.receive_later_async(raw, None, gated)
        if pending.audit is not None:
            await pending.audit  # type: ignore[misc]
        return receiver.settle(pending, None)

    async def scenario() -> tuple[Outcome, Outcome]:
        tasks = [asyncio.ensure_future(one()) for _ in range(2)]
        for _ in range(1000):
            if len(at_gate) == 2:
                break
            await asyncio.sleep(0)
        assert len(at_gate) == 2, "both copies reach the commit"
        gate.set()
        done, waiting = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        assert len(done) == 1, "the loser waits for the winner's answer"
        winner = done.pop().result()
        receiver.hold_answer(winner, 200, JSON_HEADERS, json.dumps(winner.ack).encode())
        return winner, await waiting.pop()

    winner, loser = asyncio.run(scenario())
    assert winner.accepted and receiver.keys.verifications == 2
    assert loser.retry is not None and json.loads(loser.retry.body)["duplicate"] is True
    assert receiver.stats.accepted == 1 and receiver.stats.retries == 1


def test_the_memo_is_bounded_forgets_expired_entries_and_marks_the_answer() -> None:
    signer = Signer("k", "operator", frozenset())
    memo = AnswerMemo(600)
    body = json.dumps({"status": "ok"}).encode()
    memo.hold("never-expected", 200, (), body)  # qos 0: nothing is kept, nothing is parsed
    assert len(memo) == 0
    memo.expect("old", Entry(b"d", False, NOW - 1, signer), NOW - 2)
    memo.expect("new", Entry(b"d", False, NOW + 30, signer), NOW)
    assert len(memo) == 1  # "old" expired: dropped
    big = b"x" * MAX_BODY
    for i in range(MAX_TOTAL // MAX_BODY + 10):
        memo.expect(f"m{i}", Entry(b"d", False, NOW + 30, signer), NOW)
        memo.hold(f"m{i}", 200, (), big)
    assert len(memo) <= MAX_TOTAL // MAX_BODY  # the byte budget, not the count, bounds it
    small = AnswerMemo(2)
    for name in ("a", "b", "c"):
        small.expect(name, Entry(b"d", False, NOW + 30, signer), NOW)
    assert len(small) == 2
    marker = b'{"status": "ok","duplicate":true}'  # the original's bytes, the key inserted
    held = HeldAnswer(200, (("rcan-duplicate", "true"),), marker)
    assert marked(200, [("rcan-duplicate", "true")], body) == held
    assert marked(502, (), b"not json").body == b"not json"


# --- errors ----------------------------------------------------------------------------------


def test_upstream_failed_is_a_502_nack_the_sdk_reads_as_error() -> None:
    nack = UpstreamFailedError("ConnectError", delivered="no").to_nack("m-1")
    assert (nack["code"], nack["delivered"], nack["status"]) == ("UPSTREAM_FAILED", "no", "error")
    assert UpstreamFailedError("x", delivered="unknown").http_status == 502
    response = RCANResponse.from_dict(nack)
    assert (response.status, response.msg_id) == ("error", "m-1")
    assert "new msg_id" in response.message


# --- a real gateway and the real SDK QoSManager ----------------------------------------------


ROBOT_MODULE = """\
import pathlib

CALLS = pathlib.Path(__file__).with_name("calls.txt")


def handle(envelope):
    with CALLS.open("a") as f:
        f.write(envelope["msg_id"] + "\\n")
    return {"executed": envelope["cmd"]}


def fail(envelope):
    with CALLS.open("a") as f:
        f.write(envelope["msg_id"] + "\\n")
    raise RuntimeError("arm jammed")
"""


def gateway(tmp_path: Path, pair: Any, upstream: str) -> GatewayProcess:
    """``antireplay serve`` trusting the SDK's public key, with ``upstream``."""
    tmp_path.mkdir(exist_ok=True)
    pair.save_public(tmp_path / "operator.pub")
    config = {
        "store": f"sqlite:{tmp_path / 'state.db'}",
        "audit": str(tmp_path / "audit.db"),
        "sdk_compat": True,
        "upstream": upstream,
        "keys": [{"kid": "operator", "owner": "operator", "alg": "ml-dsa-65",
                  "public_keys": [str(tmp_path / "operator.pub")], "scopes": ["control"]}],
    }  # fmt: skip
    path = tmp_path / "antireplay.yaml"
    path.write_text(yaml.safe_dump(config))
    return GatewayProcess(path)


def calls(tmp_path: Path) -> list[str]:
    path = tmp_path / "calls.txt"
    return path.read_text().split() if path.exists() else []


def qos_send(url: str, manager: QoSManager, lose_first: bool) -> Callable[[Any], None]:
    """A send_fn POSTing the message; the first reply is lost on the way back when
    ``lose_first``; an ``ok`` answer for this msg_id records the ACK."""
    replies: list[httpx.Response] = []

    def send(msg: Any) -> None:
        reply = httpx.post(url, content=msg.to_json(), headers=JSON)
        replies.append(reply)
        if lose_first and len(replies) == 1:
            return
        answer = RCANResponse.from_dict(reply.json())
        if answer.ok and answer.msg_id == msg.msg_id:
            manager.record_ack(msg.msg_id)

    send.replies = replies  # type: ignore[attr-defined]
    return send


def test_sdk_qos_manager_retry_gets_the_original_answer_upstream_called_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "robot_qos.py").write_text(ROBOT_MODULE)
    monkeypatch.chdir(tmp_path)  # the module:function upstream is imported from here
    pair = MLDSAKeyPair.generate()
    gw = gateway(tmp_path, pair, "robot_qos:handle")
    gw.start()
    try:
        manager = QoSManager(ack_timeout_s=0.2, max_retries=3)
        msg = sign_message(RCANMessage(cmd="move_forward", target=ROBOT, qos=1), pair)
        send = qos_send(f"{gw.url}/v1/messages", manager, lose_first=True)
        assert manager.send_with_ack(msg, send)
        first, again = send.replies  # type: ignore[attr-defined]
        assert (first.status_code, again.status_code) == (200, 200)
        assert again.json() == {**first.json(), "duplicate": True}
        assert again.headers["rcan-duplicate"] == "true" and "rcan-duplicate" not in first.headers
        answer = RCANResponse.from_dict(again.json())
        assert (answer.msg_id, answer.status, answer.result) == (
            msg.msg_id, "ok", {"executed": "move_forward"},
        )  # fmt: skip
        assert calls(tmp_path) == [msg.msg_id]  # executed exactly once
        metrics = httpx.get(f"{gw.url}/metrics").text
        assert "antireplay_retries_answered_total 1.0" in metrics
    finally:
        gw.stop()
    tail = CliRunner().invoke(main, ["audit", "tail", "--json", str(tmp_path / "audit.db")])
    rows = [json.loads(line) for line in tail.output.splitlines()]
    assert [(r["outcome"], r["code"], r["warning"]) for r in rows] == [
        ("state", "STATE_LOST", NO_HISTORY),  # its first start, on a state with no history
        ("accepted", None, None), ("rejected", "REPLAY_DETECTED", "QOS_RETRY"),
    ]  # fmt: skip
    report = verify(tmp_path / "audit.db")
    assert (report.broken_at, report.head) == (None, "match")


def test_an_upstream_failure_is_a_502_nack_and_its_retry_the_same_502_never_a_second_call(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "robot_qos.py").write_text(ROBOT_MODULE)
    monkeypatch.chdir(tmp_path)
    pair = MLDSAKeyPair.generate()
    raising = gateway(tmp_path / "raising", pair, "robot_qos:fail")
    nobody = gateway(tmp_path / "nobody", pair, f"http://127.0.0.1:{free_port()}/")
    raising.start()
    nobody.start()
    try:
        manager = QoSManager(ack_timeout_s=0.2, max_retries=1)
        msg = sign_message(RCANMessage(cmd="move_forward", target=ROBOT, qos=1), pair)
        send = qos_send(f"{raising.url}/v1/messages", manager, lose_first=False)
        with pytest.raises(QoSAckTimeoutError):  # never acknowledged: the action did not succeed
            manager.send_with_ack(msg, send)
        first, again = send.replies  # type: ignore[attr-defined]
        assert (first.status_code, again.status_code) == (502, 502)
        nack = first.json()
        assert (nack["code"], nack["delivered"]) == ("UPSTREAM_FAILED", "unknown")
        assert RCANResponse.from_dict(nack).status == "error"
        assert again.json() == {**nack, "duplicate": True}
        assert calls(tmp_path) == [msg.msg_id]  # the upstream was called once
        unreachable = sign_message(RCANMessage(cmd="move_forward", target=ROBOT, qos=1), pair)
        url = f"{nobody.url}/v1/messages"
        replies = [httpx.post(url, content=unreachable.to_json(), headers=JSON) for _ in "ab"]
        assert [r.status_code for r in replies] == [502, 502]
        assert replies[0].json()["delivered"] == "no"
        assert replies[1].json() == {**replies[0].json(), "duplicate": True}
        fresh = sign_message(RCANMessage(cmd="move_forward", target=ROBOT, qos=1), pair)
        retried = httpx.post(url, content=fresh.to_json(), headers=JSON)  # a new msg_id
        assert "duplicate" not in retried.json()
    finally:
        raising.stop()
        nobody.stop()


def test_a_refused_retry_keeps_the_ed25519_demo_path(receiver: Receiver) -> None:
    """A plain signed command (no qos) still gets exactly today's 409 with its reason."""
    raw = signed(key=ED)
    assert receiver.receive(raw).accepted
    again = receiver.receive(raw)
    assert again.reason == "an identical message was already accepted"
