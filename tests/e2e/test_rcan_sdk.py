"""The official RCAN SDK (rcan 3.7.0) end to end: its key files, its signatures, its safety
messages, and our answers read back with its own classes."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from click.testing import CliRunner
from cryptography.hazmat.primitives.asymmetric import mldsa
from rcan import RCANMessage, RCANResponse
from rcan.qos import make_estop_with_qos
from rcan.safety import make_estop_message
from rcan.signing import MLDSAKeyPair, sign_message, verify_message

from antireplay import ManualClock, SecurityConfig
from antireplay.audit import AuditLog
from antireplay.cli import main
from antireplay.config import AppConfig
from antireplay.core.errors import ConfigError
from antireplay.rcan.auth import load_public_key, sdk_key_id, write_key_pair
from antireplay.rcan.receive import Receiver
from antireplay.wiring import build_registry
from harness import GatewayProcess, fresh_receiver
from harness.envelopes import NOW

ROBOT = "rcan://registry.rcan.dev/acme/arm/v2/unit-001"
JSON = {"content-type": "application/json"}


def sdk_config(tmp_path: Path, pair: Any, kid: str, scopes: list[str], **extra: Any) -> Path:
    """A gateway config trusting the SDK's own public key file, as ``save_public`` wrote it."""
    pair.save_public(tmp_path / "operator.pub")
    config = {
        "store": f"sqlite:{tmp_path / 'state.db'}",
        "audit": str(tmp_path / "audit.db"),
        "sdk_compat": True,
        "keys": [
            {
                "kid": kid,
                "owner": "operator",
                "alg": "ml-dsa-65",
                "public_keys": [str(tmp_path / "operator.pub")],
                "scopes": scopes,
            },
        ],
        **extra,
    }
    path = tmp_path / "antireplay.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


@pytest.fixture
def pair() -> Any:
    return MLDSAKeyPair.generate()


@pytest.fixture
def sdk_receiver(tmp_path: Path, pair: Any, clock: ManualClock) -> Receiver:
    """SDK key file -> the one loader (``build_registry``) -> a receiver auditing to disk."""
    config = AppConfig.from_yaml(sdk_config(tmp_path, pair, "operator", ["control", "safety"]))
    audit = AuditLog(tmp_path / "audit.db")
    return fresh_receiver(SecurityConfig(), build_registry(config), None, audit, clock)


def sdk_signed(pair: Any, msg: Any = None, age_s: float = 1.0, **fields: Any) -> bytes:
    """``msg`` (default: a move command) stamped ``age_s`` before NOW, signed by the SDK."""
    if msg is None:
        msg = RCANMessage(cmd="move_forward", target=ROBOT, params={"distance_m": 1.0}, **fields)
    msg.timestamp = NOW - age_s
    return json.dumps(sign_message(msg, pair).to_dict()).encode()


# --- key files and key ids ---------------------------------------------------------------------


def test_the_sdk_public_key_file_loads_and_its_key_id_is_the_sdk_s(
    tmp_path: Path, pair: Any
) -> None:
    pair.save_public(tmp_path / "k.pub")
    assert len((tmp_path / "k.pub").read_bytes()) == 1952
    key = load_public_key((tmp_path / "k.pub").read_bytes())
    assert isinstance(key, mldsa.MLDSA65PublicKey)
    assert sdk_key_id(key) == pair.key_id
    registry = build_registry(AppConfig.from_yaml(sdk_config(tmp_path, pair, "op", ["control"])))
    # The configured kid, and the SDK's key id (the kid its sign_message always uses).
    assert registry.entries["op"] is registry.entries[pair.key_id]


def test_config_check_and_serve_load_the_same_sdk_key_files(tmp_path: Path, pair: Any) -> None:
    config = sdk_config(tmp_path, pair, pair.key_id, ["control"])
    assert CliRunner().invoke(main, ["config", "check", str(config)]).exit_code == 0
    pair.save(tmp_path / "operator.pub")  # the private key file, where the public one belongs
    refused = CliRunner().invoke(main, ["config", "check", str(config)])
    assert refused.exit_code == 2
    assert "RCAN SDK private key file" in refused.output and "save_public" in refused.output
    with pytest.raises(ConfigError, match="RCAN SDK private key file"):
        build_registry(AppConfig.from_yaml(config))


def test_an_sdk_key_id_that_names_another_key_is_a_config_error(tmp_path: Path, pair: Any) -> None:
    config = yaml.safe_load(sdk_config(tmp_path, pair, "op", ["control"]).read_text())
    write_key_pair(mldsa.MLDSA65PrivateKey.generate(), tmp_path / "x.key.pem", tmp_path / "x.pem")
    config["keys"].append({**config["keys"][0], "kid": pair.key_id, "public_keys": [
        str(tmp_path / "x.pem")]})  # fmt: skip
    with pytest.raises(ConfigError, match="names another key"):
        build_registry(AppConfig.model_validate(config))


# --- commands and safety messages ----------------------------------------------------------------


def test_sdk_command_accepted_and_its_replay_refused(sdk_receiver: Receiver, pair: Any) -> None:
    raw = sdk_signed(pair)
    assert sdk_receiver.receive(raw).accepted
    replay = sdk_receiver.receive(raw)
    assert (replay.status, replay.code) == (409, "REPLAY_DETECTED")


@pytest.mark.parametrize(
    "build",
    [
        lambda: make_estop_with_qos(ROBOT, "worker in the cell"),  # qos=2, unsigned: ignored
        lambda: RCANMessage(cmd="ESTOP", target=ROBOT, params={"reason": "worker in the cell"}),
    ],
    ids=["make_estop_with_qos", "cmd-ESTOP"],
)
def test_sdk_estop_is_processed_and_a_fresh_duplicate_flagged(
    sdk_receiver: Receiver, pair: Any, build: Any
) -> None:
    raw = sdk_signed(pair, build())
    first = sdk_receiver.receive(raw)
    assert first.accepted and first.warning is None
    again = sdk_receiver.receive(raw)
    assert (again.accepted, again.status, again.warning) == (True, 200, "REPLAY_DETECTED")
    assert sdk_receiver.audit is not None
    first_row, dup_row = sdk_receiver.audit.tail(2)
    assert (first_row.msg_type, first_row.warning) == (6, None)
    assert (dup_row.outcome, dup_row.msg_type, dup_row.warning) == (
        "accepted", 6, "REPLAY_DETECTED",
    )  # fmt: skip


@pytest.mark.parametrize("cmd", ["ESTOP", "STOP", "RESUME"])
def test_sdk_safety_commands_get_the_safety_window(
    sdk_receiver: Receiver, pair: Any, cmd: str
) -> None:
    """11 s old: fine for a command (30 s window), stale for SAFETY (10 s), ESTOP included."""
    assert sdk_receiver.receive(sdk_signed(pair, age_s=11)).accepted
    stale = sdk_receiver.receive(sdk_signed(pair, RCANMessage(cmd=cmd, target=ROBOT), age_s=11))
    assert (stale.status, stale.code) == (408, "MESSAGE_STALE")
    assert sdk_receiver.receive(sdk_signed(pair, RCANMessage(cmd=cmd, target=ROBOT))).accepted


def test_sdk_safety_commands_need_the_safety_scope(
    tmp_path: Path, pair: Any, clock: ManualClock
) -> None:
    config = AppConfig.from_yaml(sdk_config(tmp_path, pair, "op", ["control"]))
    rx = fresh_receiver(SecurityConfig(), build_registry(config), None, None, clock)
    assert rx.receive(sdk_signed(pair)).accepted
    out = rx.receive(sdk_signed(pair, RCANMessage(cmd="ESTOP", target=ROBOT)))
    assert (out.status, out.code) == (403, "SCOPE_DENIED")


def test_a_captured_sdk_command_cannot_be_turned_into_an_estop(
    sdk_receiver: Receiver, pair: Any
) -> None:
    raw = sdk_signed(pair)
    genuine = json.loads(raw)
    forgeries = {
        "cmd": ({**genuine, "cmd": "ESTOP"}, 401, "SIGNATURE_INVALID"),
        "params": (
            {**genuine, "params": {**genuine["params"], "safety_event": "ESTOP"}},
            401,
            "SIGNATURE_INVALID",
        ),
        "type": ({**genuine, "type": 6, "safety_event": "ESTOP"}, 403, "SCOPE_DENIED"),
    }
    for name, (body, status, code) in forgeries.items():
        out = sdk_receiver.receive(json.dumps(body).encode())
        assert (out.status, out.code) == (status, code), name
    assert sdk_receiver.receive(raw).accepted  # the genuine command was not spent
    # Once spent, no relabelling buys the ESTOP exemption: the forgery is still refused.
    late = sdk_receiver.receive(json.dumps(forgeries["type"][0]).encode())
    assert not late.accepted and late.warning is None


def test_a_contradicting_safety_event_is_refused(sdk_receiver: Receiver, pair: Any) -> None:
    msg = RCANMessage(cmd="ESTOP", target=ROBOT, params={"safety_event": "RESUME"})
    out = sdk_receiver.receive(sdk_signed(pair, msg))
    assert (out.status, out.code) == (400, "INVALID_ENVELOPE")


def test_the_sdk_s_unsigned_safety_dict_is_refused_with_the_signed_way(
    sdk_receiver: Receiver,
) -> None:
    out = sdk_receiver.receive(json.dumps(make_estop_message(ROBOT, "stop")).encode())
    assert (out.status, out.code) == (400, "INVALID_ENVELOPE")
    assert "cmd ESTOP" in (out.reason or "")


# --- answers read back with the SDK's classes -------------------------------------------------


def test_nack_and_ack_read_back_with_the_sdk_classes(sdk_receiver: Receiver, pair: Any) -> None:
    raw = sdk_signed(pair)
    ok = sdk_receiver.receive(raw)
    nack_out = sdk_receiver.receive(raw)
    msg_id = json.loads(raw)["msg_id"]
    ack, nack = ok.ack, nack_out.nack
    assert ack is not None and nack is not None and ok.nack is None and nack_out.ack is None
    for answer, status in ((ack, "ok"), (nack, "error")):
        wire = json.loads(json.dumps(answer))
        RCANMessage.from_dict(wire)  # must not raise
        response = RCANResponse.from_dict(wire)
        assert (response.msg_id, response.status) == (msg_id, status)
    assert RCANResponse.from_dict(nack).message == nack["reason"]
    # The SDK keeps only ``message``: the code leads it, so an SDK user sees why.
    assert nack["reason"] == "REPLAY_DETECTED: an identical message was already accepted"
    # What RCAN §8.3 and the README rely on is all still there.
    assert (nack["type"], nack["code"], nack["ref_msg_id"]) == (18, "REPLAY_DETECTED", msg_id)
    assert (ack["type"], ack["accepted"], ack["ref_msg_id"]) == (17, True, msg_id)


# --- antireplay sign --sdk --------------------------------------------------------------------


def test_sign_sdk_output_verifies_with_the_sdk_and_the_receiver(
    tmp_path: Path, pair: Any, clock: ManualClock
) -> None:
    pem = mldsa.MLDSA65PrivateKey.generate()
    write_key_pair(pem, tmp_path / "op.key.pem", tmp_path / "op.pub.pem")
    pair.save(tmp_path / "sdk.key")
    trusted = MLDSAKeyPair.from_public_bytes(pem.public_key().public_bytes_raw())
    for key_file, sdk_pub in ((tmp_path / "op.key.pem", trusted), (tmp_path / "sdk.key", pair)):
        args = ["sign", "--sdk", "--key", str(key_file), "--cmd", "ESTOP", "--target", ROBOT,
                "--param", "reason=drill"]  # fmt: skip
        result = CliRunner().invoke(main, args)
        assert result.exit_code == 0, result.output
        body = json.loads(result.output)
        verify_message(RCANMessage.from_dict(body), [sdk_pub])  # raises if it does not verify
        assert body["sig"]["kid"] == sdk_pub.key_id
        config = sdk_config(tmp_path, sdk_pub, "op", ["control", "safety"])
        registry = build_registry(AppConfig.from_yaml(config))
        body["timestamp"] = NOW - 1
        resigned = CliRunner().invoke(
            main, ["sign", "--sdk", "--key", str(key_file), "--json", "-"], input=json.dumps(body)
        )
        rx = fresh_receiver(SecurityConfig(), registry, None, None, clock)
        out = rx.receive(resigned.output.encode())
        assert out.accepted, out.reason


def test_sign_sdk_refuses_what_the_sdk_does_not_sign(tmp_path: Path) -> None:
    write_key_pair(mldsa.MLDSA65PrivateKey.generate(), tmp_path / "k.pem", tmp_path / "k.pub")
    base = ["sign", "--sdk", "--key", str(tmp_path / "k.pem"), "--cmd", "c", "--target", ROBOT]
    for extra, needle in (
        (["--type", "6"], "type"),
        (["--safety-event", "ESTOP"], "safety_event"),
        (["--scope", "safety"], "scope"),
        (["--kid", "other"], "SDK key id"),
    ):
        result = CliRunner().invoke(main, [*base, *extra])
        assert result.exit_code == 2 and needle in result.output, result.output


# --- the gateway process ---------------------------------------------------------------------


def test_serve_with_sdk_keys_end_to_end(tmp_path: Path, pair: Any) -> None:
    """SDK key file -> ``serve`` -> SDK-signed command 200, replay 409 (NACK read by the SDK),
    SDK ESTOP 200 and its fresh duplicate 200 with the warning."""
    gw = GatewayProcess(sdk_config(tmp_path, pair, "operator", ["control", "safety"]))
    gw.start()
    try:
        msg = sign_message(RCANMessage(cmd="move_forward", target=ROBOT), pair)
        url = f"{gw.url}/v1/messages"
        accepted = httpx.post(url, content=msg.to_json(), headers=JSON)
        assert accepted.status_code == 200
        ack = RCANResponse.from_dict(accepted.json())  # the COMMAND_ACK, read by the SDK
        assert (ack.msg_id, ack.status) == (msg.msg_id, "ok")
        replay = httpx.post(url, content=msg.to_json(), headers=JSON)
        assert replay.status_code == 409
        assert RCANResponse.from_dict(replay.json()).msg_id == msg.msg_id
        estop = sign_message(make_estop_with_qos(ROBOT, "drill"), pair).to_json()
        assert httpx.post(url, content=estop, headers=JSON).status_code == 200
        again = httpx.post(url, content=estop, headers=JSON)
        assert (again.status_code, again.json().get("warning")) == (200, "REPLAY_DETECTED")
    finally:
        gw.stop()
