"""The receive pipeline: §8.3 order, check -> authenticate -> commit, NACKs, audit."""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import sqlite3
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from antireplay import ManualClock, SecurityConfig
from antireplay.audit import AuditLog, verify
from antireplay.cli.demo import command, load_operator_key, write_demo_config
from antireplay.rcan.auth import JwtVerifier, sign_envelope
from antireplay.rcan.envelope import SDK_SIGNED_FIELDS, encode
from antireplay.rcan.receive import Outcome, Receiver
from antireplay.rcan.steps import audit_row
from harness import fresh_receiver, post, race, serving
from harness.envelopes import (
    ED,
    JWT_KEY,
    MITM_FIELDS,
    NOW,
    PQ,
    PQ87,
    VIEWER,
    codes,
    message,
    registry,
    sdk_message,
    sdk_registry,
    signed,
    token,
)
from harness.stores import aged_state, sqlite_store

# --- acceptance and the basic answers ------------------------------------------------------------


@pytest.mark.parametrize(
    ("kid", "key", "alg"),
    [
        ("op-ed", ED, "ed25519"),
        ("op-pq", PQ, "ml-dsa-65"),
        ("op-87", PQ87, "ml-dsa-87"),
        ("op-hy", (ED, PQ), "ed25519+ml-dsa-65"),
    ],
)
def test_fresh_signed_message_accepted(receiver: Receiver, kid: str, key: Any, alg: str) -> None:
    out = receiver.receive(signed(kid, key, alg))
    assert codes(out) == (True, 200, None)
    assert out.signer is not None and out.signer.owner == "operator"


def test_exact_replay_is_409_with_nack(receiver: Receiver) -> None:
    raw = signed()
    assert receiver.receive(raw).accepted
    out = receiver.receive(raw)
    assert codes(out) == (False, 409, "REPLAY_DETECTED")
    assert out.nack is not None
    assert out.nack["type"] == 18 and out.nack["code"] == "REPLAY_DETECTED"
    assert out.nack["ref_msg_id"] == json.loads(raw)["msg_id"]


def test_legacy_nack_type_31(tmp_path: Path, clock: ManualClock) -> None:
    rx = fresh_receiver(SecurityConfig(nack_type=31), registry(), None, None, clock)
    raw = signed()
    rx.receive(raw)
    nack = rx.receive(raw).nack
    assert nack is not None and nack["type"] == 31


def test_stale_is_408(receiver: Receiver) -> None:
    assert codes(receiver.receive(signed(timestamp=NOW - 31))) == (False, 408, "MESSAGE_STALE")


def test_timestamp_ms_accepted_and_exact(receiver: Receiver) -> None:
    raw = signed(timestamp=None, timestamp_ms=int((NOW - 2) * 1000))
    body = json.loads(raw)
    body.pop("timestamp")
    body = sign_envelope({k: v for k, v in body.items() if k != "sig"}, "op-ed", "ed25519", ED)
    assert receiver.receive(json.dumps(body).encode()).accepted


# --- every step's rejection, in order -------------------------------------------------------------


def test_steps_reject_in_order(receiver: Receiver) -> None:
    huge = json.dumps(message(params={"blob": "x" * 70_000})).encode()
    deep: dict[str, Any] = {}
    for _ in range(30):
        deep = {"d": deep}
    cases = [
        (b"not json", "INVALID_ENVELOPE"),
        (b"[1,2,3]", "INVALID_ENVELOPE"),
        (huge, "INVALID_ENVELOPE"),
        (json.dumps(message(params=deep)).encode(), "INVALID_ENVELOPE"),
        (json.dumps({**message(), "surprise": 1}).encode(), "INVALID_ENVELOPE"),
        (signed(rcan="2.0", rcan_version="2.0"), "VERSION_INCOMPATIBLE"),
        (signed(msg_id=""), "INVALID_MESSAGE_ID"),
        (signed(timestamp="nan"), "INVALID_TIMESTAMP"),
        (signed(timestamp=NOW + 60), "MESSAGE_FROM_FUTURE"),
        (json.dumps(message()).encode(), "SIGNATURE_REQUIRED"),
        (signed("viewer", VIEWER), "SCOPE_DENIED"),
    ]
    for raw, code in cases:
        out = receiver.receive(raw)
        assert (out.accepted, out.code) == (False, code), (code, out.reason)
        assert 400 <= out.status < 500


def test_stale_and_badly_signed_reports_stale(receiver: Receiver) -> None:
    bad = json.loads(signed(timestamp=NOW - 100))
    bad["sig"]["value"] = "AAAA"
    assert receiver.receive(json.dumps(bad).encode()).code == "MESSAGE_STALE"


def test_bad_version_and_stale_reports_version(receiver: Receiver) -> None:
    raw = signed(timestamp=NOW - 100, rcan="9.0", rcan_version="9.0")
    out = receiver.receive(raw)
    assert (out.code, out.status) == ("VERSION_INCOMPATIBLE", 426)


def test_replay_and_stale_paths_do_no_crypto(tmp_path: Path, clock: ManualClock) -> None:
    keys = registry()
    jwt_verifier = JwtVerifier({"jwt-1": JWT_KEY.public_key()}, clock=clock)
    rx = fresh_receiver(SecurityConfig(), keys, None, None, clock, jwt=jwt_verifier)
    raw = signed()
    rx.receive(raw, {"Authorization": f"Bearer {token()}"})
    before = (keys.verifications, jwt_verifier.decodes)
    for _ in range(50):
        assert rx.receive(raw, {"Authorization": f"Bearer {token()}"}).code == "REPLAY_DETECTED"
        stale = signed(timestamp=NOW - 100)
        assert rx.receive(stale, {"Authorization": f"Bearer {token()}"}).code == "MESSAGE_STALE"
    assert (keys.verifications, jwt_verifier.decodes) == before


# --- cache poisoning and signature coverage -------------------------------------------------------


def test_forged_message_cannot_poison_the_cache(receiver: Receiver) -> None:
    genuine = json.loads(signed())
    forged = {**genuine, "cmd": "self_destruct"}
    assert codes(receiver.receive(json.dumps(forged).encode()))[2] == "SIGNATURE_INVALID"
    assert receiver.receive(json.dumps(genuine).encode()).accepted


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("qos", 2),
        ("scope", "admin"),
        ("type", 6),
        ("target", "rcan://other"),
        ("timestamp", NOW - 2),
        ("sender", "someone-else"),
        ("params", {"distance_m": 100.0}),
    ],
)
def test_policy_fields_are_covered_by_the_signature(
    receiver: Receiver, field: str, value: Any
) -> None:
    body = json.loads(signed())
    body[field] = value
    assert receiver.receive(json.dumps(body).encode()).code == "SIGNATURE_INVALID"


def test_the_safety_event_is_covered_by_the_signature(receiver: Receiver) -> None:
    body = json.loads(signed(type=6, safety_event="STOP", cmd="halt"))
    body["safety_event"] = "ESTOP"
    assert receiver.receive(json.dumps(body).encode()).code == "SIGNATURE_INVALID"


# --- ESTOP end to end ----------------------------------------------------------------------------


def test_estop_invariant_end_to_end(tmp_path: Path, receiver: Receiver) -> None:
    estop = signed(type=6, safety_event="ESTOP", cmd="estop")
    assert codes(receiver.receive(estop)) == (True, 200, None)
    again = receiver.receive(estop)
    assert again.accepted and again.warning == "REPLAY_DETECTED"
    stale = signed(type=6, safety_event="ESTOP", cmd="estop", timestamp=NOW - 11)
    assert receiver.receive(stale).code == "MESSAGE_STALE"
    resume = signed(type=6, safety_event="RESUME", cmd="resume")
    assert receiver.receive(resume).accepted
    assert receiver.receive(resume).code == "REPLAY_DETECTED"
    assert receiver.audit is not None
    warned = [r for r in receiver.audit.tail(50) if r.warning == "REPLAY_DETECTED"]
    assert len(warned) == 1 and warned[0].outcome == "accepted"


def test_safety_needs_the_safety_scope(receiver: Receiver) -> None:
    out = receiver.receive(signed("op-87", PQ87, "ml-dsa-87", type=6, safety_event="ESTOP"))
    assert out.code == "SCOPE_DENIED" and out.status == 403


# --- races --------------------------------------------------------------------------------------


def test_copies_racing_through_crypto_one_wins(receiver: Receiver) -> None:
    for _ in range(20):
        raw = signed("op-pq", PQ, "ml-dsa-65")
        outcomes: list[Outcome] = []

        def deliver(r: bytes = raw, out: list[Outcome] = outcomes) -> None:
            out.append(receiver.receive(r))

        race(6, deliver)
        assert sorted(o.code or "OK" for o in outcomes) == ["OK"] + ["REPLAY_DETECTED"] * 5


# --- the official RCAN SDK --------------------------------------------------------------------


@pytest.mark.parametrize("field", [{"sequence_number": 1}, {"scope": "control"}])
def test_compat_mode_refuses_unsigned_policy_fields(clock: ManualClock, field: Any) -> None:
    raw, pair = sdk_message(**field)
    compat = fresh_receiver(SecurityConfig(), sdk_registry(pair, True), None, None, clock)
    assert compat.receive(raw).code == "SCOPE_DENIED"


@pytest.mark.parametrize("name", sorted(MITM_FIELDS))
def test_compat_mode_refuses_every_field_the_sdk_does_not_sign(
    clock: ManualClock, name: str
) -> None:
    raw, pair = sdk_message()
    compat = fresh_receiver(SecurityConfig(), sdk_registry(pair, True), None, None, clock)
    body = {**json.loads(raw), name: MITM_FIELDS[name]}
    out = compat.receive(json.dumps(body).encode())
    # A safety_event on the SDK's COMMAND is malformed before any signature is read.
    refusal = ("INVALID_ENVELOPE", 400) if name == "safety_event" else ("SCOPE_DENIED", 403)
    assert (out.code, out.status) == refusal
    assert name in (out.reason or "")
    assert compat.receive(raw).accepted  # the genuine message was not spent by the forgery


def test_compat_mode_forwards_exactly_the_signed_fields(clock: ManualClock) -> None:
    raw, pair = sdk_message()
    compat = fresh_receiver(SecurityConfig(), sdk_registry(pair, True), None, None, clock)
    out = compat.receive(raw)
    assert out.accepted and out.envelope is not None
    forwarded = json.loads(encode(out.envelope))
    assert set(forwarded) == {*SDK_SIGNED_FIELDS, "rcan_version", "sig"}
    assert forwarded["rcan_version"] == forwarded["rcan"]


def test_compat_mode_tolerates_the_qos_hint_and_never_forwards_it(clock: ManualClock) -> None:
    """``qos`` is the SDK's unsigned delivery hint: no policy reads it, so it is dropped."""
    raw, pair = sdk_message(qos=2)
    compat = fresh_receiver(SecurityConfig(), sdk_registry(pair, True), None, None, clock)
    out = compat.receive(raw)
    assert out.accepted and out.envelope is not None
    assert "qos" not in json.loads(encode(out.envelope))


def test_compat_mode_tampered_unsigned_field_is_refused(clock: ManualClock) -> None:
    raw, pair = sdk_message()
    body = json.loads(raw)
    body["type"], body["safety_event"] = 6, "ESTOP"  # not covered by the SDK signature
    compat = fresh_receiver(SecurityConfig(), sdk_registry(pair, True), None, None, clock)
    assert compat.receive(json.dumps(body).encode()).code == "SCOPE_DENIED"


# --- audit trail -------------------------------------------------------------------------------


def test_garbage_flood_audit_is_rate_limited(tmp_path: Path, receiver: Receiver) -> None:
    for _ in range(100):
        receiver.receive(b"{")
    assert receiver.audit is not None
    assert receiver.audit.count() <= 11
    assert receiver.stats.rejected["INVALID_ENVELOPE"] == 100
    assert receiver.stats.unaudited >= 89


# --- fuzzing ----------------------------------------------------------------------------------

JSONISH = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda kids: (
        st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=8), kids, max_size=4)
    ),
    max_leaves=12,
)
FIELDS = st.sampled_from(
    ["msg_id", "timestamp", "timestamp_ms", "cmd", "target", "rcan", "rcan_version", "type",
     "safety_event", "params", "sig", "scope", "qos", "sender", "jwt", "extra"]
)  # fmt: skip
FUZZ_RX = fresh_receiver(SecurityConfig(), registry(), None, None, ManualClock(wall=NOW))


def _check_outcome(out: Outcome) -> None:
    assert isinstance(out, Outcome)
    if not out.accepted:
        assert 400 <= out.status < 500 and out.code


@settings(max_examples=6_000, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.binary(max_size=300))
def test_fuzz_bytes_only_typed_rejections(raw: bytes) -> None:
    _check_outcome(FUZZ_RX.receive(raw))


@settings(max_examples=6_000, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.dictionaries(FIELDS, JSONISH, max_size=10), st.booleans())
def test_fuzz_envelopes_only_typed_rejections(body: dict[str, Any], base: bool) -> None:
    doc = {**message(), **body} if base else body
    try:
        raw = json.dumps(doc).encode()
    except ValueError:
        return
    _check_outcome(FUZZ_RX.receive(raw))


def test_exact_copy_memo_and_its_limits(receiver: Receiver, clock: ManualClock) -> None:
    raw = signed()
    assert receiver.receive(raw).accepted
    assert receiver.receive(raw).code == "REPLAY_DETECTED"  # byte-identical: caught before parsing
    reserialized = json.dumps(json.loads(raw), indent=1).encode()
    assert receiver.receive(reserialized).code == "REPLAY_DETECTED"  # same message, other bytes
    clock.advance(31)
    assert receiver.receive(raw).code == "MESSAGE_STALE"  # the memo never outlives the window
    assert receiver.audit is not None
    codes_seen = [r.code for r in receiver.audit.tail(10)]
    assert codes_seen == [None, "REPLAY_DETECTED", "REPLAY_DETECTED", "MESSAGE_STALE"]


def test_rejected_messages_never_enter_the_copy_memo(receiver: Receiver) -> None:
    body = json.loads(signed())
    forged = json.dumps({**body, "cmd": "arm"}).encode()
    assert receiver.receive(forged).code == "SIGNATURE_INVALID"
    assert receiver.receive(forged).code == "SIGNATURE_INVALID"  # not REPLAY: never accepted


def test_unauditable_accept_is_refused_not_lost(tmp_path: Path, receiver: Receiver) -> None:
    assert receiver.audit is not None
    receiver.audit.close()  # the audit database is gone (disk full, unmounted…)
    out = receiver.receive(signed())
    assert (out.accepted, out.status, out.code) == (False, 503, "STATE_UNAVAILABLE")
    assert receiver.stats.accepted == 0
    assert receiver.stats.audit_failures == 2  # the accept, then its 503 answer
    assert receiver.receive(signed(timestamp=NOW - 100)).code == "MESSAGE_STALE"


def test_an_estop_is_delivered_while_the_audit_trail_cannot_be_written(
    tmp_path: Path, receiver: Receiver, caplog: pytest.LogCaptureFixture
) -> None:
    """The trail moved away under its writer (which then refuses to append): a fresh ESTOP
    is delivered with a warning, said once, counted, its row held; a duplicate copy is
    still the flagged one; other messages get 503.  Back in place, the next durable row
    brings the held rows into the trail."""
    assert receiver.audit is not None and receiver.receive(signed()).accepted
    trail, aside = tmp_path / "audit.db", tmp_path / "aside.db"
    trail.rename(aside)
    estop = signed(type=6, safety_event="ESTOP", cmd="estop")
    with caplog.at_level(logging.WARNING, logger="antireplay.rcan.receive"):
        first = receiver.receive(estop)
        again = receiver.receive(estop)
        other = receiver.receive(signed(type=6, safety_event="ESTOP", cmd="halt"))
        refused = receiver.receive(signed())
    assert (first.accepted, first.warning) == (True, "AUDIT_UNAVAILABLE")
    assert first.ack is not None and first.ack["warning"] == "AUDIT_UNAVAILABLE"
    assert (again.accepted, again.warning) == (True, "REPLAY_DETECTED")
    assert (other.accepted, other.warning) == (True, "AUDIT_UNAVAILABLE")
    assert (refused.accepted, refused.status, refused.code) == (False, 503, "STATE_UNAVAILABLE")
    said = [r for r in caplog.records if r.name == "antireplay.rcan.receive" and r.levelno >= 40]
    assert len(said) == 1 and "audit trail unavailable" in said[0].getMessage()
    assert (receiver.stats.held_estops, receiver.held_rows) == (3, 3)
    aside.rename(trail)
    assert receiver.receive(signed()).accepted  # a durable row: the held ones are queued
    assert receiver.held_rows == 0
    assert receiver.receive(signed()).accepted  # queued behind them: they are durable now
    rows = [r for r in receiver.audit.tail(20) if r.msg_type == 6]
    assert [(r.outcome, r.warning) for r in rows] == [
        ("accepted", "AUDIT_UNAVAILABLE"), ("accepted", "REPLAY_DETECTED"),
        ("accepted", "AUDIT_UNAVAILABLE"),
    ]  # fmt: skip
    assert verify(trail).ok


@pytest.mark.parametrize("driver", ["thread", "event loop"])
def test_a_fresh_estop_is_prompt_while_another_process_holds_the_state_lock(
    tmp_path: Path, clock: ManualClock, driver: str
) -> None:
    """Another connection holds the state database's write lock (``BEGIN IMMEDIATE``: a
    second gateway on the same state dir, stopped mid-batch): a fresh ESTOP is delivered
    flagged within a bound far below the 10 s busy timeout (it took two of them), and its
    row, spilled, reaches the trail once the lock is released."""
    store = sqlite_store(tmp_path / "state.db", clock=clock)  # the default 10 s busy timeout
    audit = AuditLog(tmp_path / "audit.db")
    audit.attach(store.outbox())
    receiver = fresh_receiver(SecurityConfig(), registry(), store, audit, clock)
    assert receiver.receive(signed()).accepted
    estop = signed(type=6, safety_event="ESTOP", cmd="estop")

    async def on_loop() -> Outcome:
        async def offload(fn: Callable[..., Any], *args: Any) -> Any:
            return await asyncio.to_thread(fn, *args)

        return await receiver.receive_async(estop, None, offload, offload)

    holder = sqlite3.connect(tmp_path / "state.db", isolation_level=None)
    holder.execute("BEGIN IMMEDIATE")
    try:
        start = time.monotonic()
        out = receiver.receive(estop) if driver == "thread" else asyncio.run(on_loop())
        took = time.monotonic() - start
    finally:
        holder.rollback()
        holder.close()
    assert (out.accepted, out.warning) == (True, "STATE_UNAVAILABLE")
    assert took < 2.0  # two SAFETY_WAIT_S and a spill; 20 s before
    assert receiver.receive(signed()).accepted  # the lock is free: the spill is merged
    receiver.close()
    rows = [(r.outcome, r.warning) for r in AuditLog(tmp_path / "audit.db").tail(20)
            if r.msg_type == 6]  # fmt: skip
    assert rows == [("accepted", "STATE_UNAVAILABLE")]  # once: withdrawn from the outbox
    assert verify(tmp_path / "audit.db").ok
    store.close()


def test_a_refused_replay_is_audited_under_the_key_it_claims_and_verified_only_if_checked(
    tmp_path: Path,
) -> None:
    """A replay is refused before its signature is checked, so its row names the key id it
    claims (``kid:operator``, unverified), never ``-`` and never an authentication that did
    not happen.  After a restart the first copy of an accepted msg_id reaches the signature
    once (the commit is the authority): a tampered copy is ``SIGNATURE_INVALID``, the intact
    one ``REPLAY_DETECTED`` under its verified sender; later copies are refused before it."""
    config = write_demo_config(tmp_path)
    raw = command(load_operator_key(tmp_path))
    tampered = json.dumps({**json.loads(raw), "params": {"distance_m": 9}}).encode()
    aged_state(tmp_path / "state.db")  # history: no first start's fence
    with serving(config) as gateway:
        assert post(gateway, raw).status_code == 200
        assert post(gateway, raw).status_code == 409  # the byte-identical copy: no parse
    with serving(config) as gateway:
        assert post(gateway, tampered).json()["code"] == "SIGNATURE_INVALID"
        assert post(gateway, raw).json()["code"] == "REPLAY_DETECTED"  # verified, then refused
        assert post(gateway, raw).json()["code"] == "REPLAY_DETECTED"  # known: no crypto
    tail = [sys.executable, "-m", "antireplay", "audit", "tail", str(tmp_path / "audit.db")]
    rows = [json.loads(line) for line in subprocess.run(
        [*tail, "--json"], capture_output=True, text=True, timeout=60, check=True,
    ).stdout.splitlines()]  # fmt: skip
    seen = [(r["code"], r["sender"], r["sender_verified"]) for r in rows]
    assert seen == [
        (None, "operator", True),
        ("REPLAY_DETECTED", "kid:operator", False),
        ("SIGNATURE_INVALID", "kid:operator", False),
        ("REPLAY_DETECTED", "operator", True),
        ("REPLAY_DETECTED", "kid:operator", False),
    ]
    table = subprocess.run(tail, capture_output=True, text=True, timeout=60, check=True).stdout
    assert "kid:operator (claimed)" in table


def test_a_folded_refusal_builds_no_audit_row(
    receiver: Receiver, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A flood of copies: the refusal auditor admits a few rows and folds the rest; a row
    is built only for those it admits (the folded ones cost no row, no wall clock read)."""
    built: list[object] = []
    real = audit_row

    def counting(*args: Any, **kwargs: Any) -> Any:
        built.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr("antireplay.rcan.receive_shared.audit_row", counting)
    raw = signed()
    assert receiver.receive(raw).accepted
    built.clear()
    outcomes = [receiver.receive(raw) for _ in range(200)]
    assert all(o.code == "REPLAY_DETECTED" for o in outcomes)
    assert receiver.stats.unaudited >= 150  # folded into the summary
    assert len(built) == 200 - receiver.stats.unaudited  # one row per admitted refusal


def test_an_accepted_command_on_a_thread_is_one_durable_trip_like_the_loops(
    tmp_path: Path, clock: ManualClock
) -> None:
    """The thread driver takes the loop driver's paired path: with the trail's outbox in
    the SQLite store, an accepted command's entry and row are ONE committer operation (two
    before); racing twins on threads get one acceptance and one refusal row; an ESTOP still
    takes its two bounded steps; the chain verifies."""
    store = sqlite_store(tmp_path / "state.db", clock=clock)
    audit = AuditLog(tmp_path / "audit.db", clock=clock)
    audit.attach(store.outbox())
    receiver = fresh_receiver(SecurityConfig(), registry(), store, audit, clock)
    committer = store.group_commit
    before = committer.operations
    assert receiver.receive(signed(msg_id="thread-1")).accepted
    assert committer.operations - before == 1  # the entry and its row: one operation
    twins = [signed(msg_id="twin", cmd=c) for c in ("a", "b")]
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        raced = list(pool.map(receiver.receive, twins))
    assert sorted((o.accepted, o.code or "") for o in raced) == [
        (False, "REPLAY_DETECTED"),
        (True, ""),
    ]
    before = committer.operations
    assert receiver.receive(signed(type=6, safety_event="ESTOP", cmd="estop")).accepted
    assert committer.operations - before == 2  # its entry, then its row (spillable)
    receiver.close()
    rows = AuditLog(tmp_path / "audit.db").tail(20)
    assert [r.outcome for r in rows if r.msg_id == "thread-1"] == ["accepted"]
    twin = sorted((r.outcome, r.code or "") for r in rows if r.msg_id == "twin")
    assert twin == [("accepted", ""), ("rejected", "REPLAY_DETECTED")]
    assert verify(tmp_path / "audit.db").ok
    store.close()
