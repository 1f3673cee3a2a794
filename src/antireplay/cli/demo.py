"""The operator-and-attacker demo, against a real gateway process or an in-process cache.

Each step states what the robot must answer and what it did answer; the demo
fails (non-zero exit in the CLI) if any step differs.

* :func:`run_gateway_demo` (``antireplay demo``) starts ``antireplay serve`` on a
  free loopback port with a temporary state directory (:func:`start_gateway`),
  waits for ``/readyz`` (a new state fences its first start), plays operator and
  attacker over HTTP, reads the replay state's size from the gateway's ``/metrics``
  (as an operator would), restarts the gateway, and checks the audit chain.
* :func:`run_window_demo` (``antireplay demo --in-process``) exercises the §8.3
  window alone with a :class:`ManualClock`: deterministic and instant.
"""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import yaml
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ed25519

from antireplay.audit import ChainReport, verify
from antireplay.core.clock import ManualClock
from antireplay.core.errors import ReplayAttackError
from antireplay.core.messages import MessageType, SafetyEvent
from antireplay.rcan.auth import sign_envelope, write_key_pair
from antireplay.state.replay import ReplayCache

ACCEPTED = "accepted"


@dataclass(frozen=True)
class StepResult:
    """One demo step: what the robot must answer and what it answered."""

    step: str
    expected: str
    got: str

    @property
    def ok(self) -> bool:
        return self.expected == self.got


def _answer(action: Callable[[], object]) -> str:
    try:
        verdict = action()
    except ReplayAttackError as exc:
        return f"{exc.code} ({exc.http_status})"
    warning = getattr(verdict, "warning", None)
    return ACCEPTED if warning is None else f"{ACCEPTED}, warning {warning}"


def run_window_demo() -> list[StepResult]:
    """Play the operator and the attacker against one receiver; return every step."""
    clock = ManualClock(wall=1_800_000_000.0)
    cache = ReplayCache(window_s=30, max_size=1_000, clock=clock)
    clock.advance(6)  # past the new receiver's restart fence (start + skew)
    t0 = clock.wall()
    cmd, safety, estop = MessageType.COMMAND, MessageType.SAFETY, SafetyEvent.ESTOP
    steps: list[tuple[str, str, Callable[[], object]]] = [
        ("operator: move_forward", ACCEPTED, lambda: cache.commit("cmd-1", t0, cmd)),
        ("attacker: exact replay", "REPLAY_DETECTED (409)", lambda: cache.commit("cmd-1", t0, cmd)),
        ("attacker: 40 s old capture", "MESSAGE_STALE (408)", lambda: cache.commit("old", t0 - 40)),
        (
            "attacker: stamped 60 s ahead",
            "MESSAGE_FROM_FUTURE (400)",
            lambda: cache.commit("f", t0 + 60),
        ),
        ("attacker: timestamp 'nan'", "INVALID_TIMESTAMP (400)", lambda: cache.commit("n", "nan")),
        ("operator: SAFETY STOP", ACCEPTED, lambda: cache.commit("stop-1", t0, safety, "STOP")),
    ]
    results = [StepResult(name, want, _answer(act)) for name, want, act in steps]
    clock.advance(15)
    results.append(
        StepResult(
            "attacker: replay 15 s old command after a SAFETY msg",
            "REPLAY_DETECTED (409)",
            _answer(lambda: cache.commit("cmd-1", t0, cmd)),
        )
    )
    now = clock.wall()
    flooded = ReplayCache(window_s=30, max_size=1_000, clock=clock)
    clock.advance(6)
    now = clock.wall()
    flooded.commit("cmd-2", now, cmd)
    for i in range(5_000):
        try:
            flooded.commit(f"flood-{i}", now + 5)
        except ReplayAttackError:
            break
    results.append(
        StepResult(
            f"attacker: 5000-id flood, then replay (cache holds {len(flooded)})",
            "MESSAGE_STALE (408)",
            _answer(lambda: flooded.commit("cmd-2", now, cmd)),
        )
    )
    results += [
        StepResult(
            "operator: ESTOP", ACCEPTED, _answer(lambda: cache.commit("e-1", now, safety, estop))
        ),
        StepResult(
            "network: duplicate fresh ESTOP",
            f"{ACCEPTED}, warning REPLAY_DETECTED",
            _answer(lambda: cache.commit("e-1", now, safety, estop)),
        ),
        StepResult(
            "attacker: 11 s old ESTOP",
            "MESSAGE_STALE (408)",
            _answer(lambda: cache.commit("e-old", now - 11, safety, estop)),
        ),
        StepResult(
            "operator: RESUME",
            ACCEPTED,
            _answer(lambda: cache.commit("r-1", now, safety, "RESUME")),
        ),
        StepResult(
            "attacker: replay RESUME",
            "REPLAY_DETECTED (409)",
            _answer(lambda: cache.commit("r-1", now, safety, "RESUME")),
        ),
    ]
    return results


def robot(envelope: dict[str, Any]) -> dict[str, Any]:
    """The demo's stand-in robot API (the gateway's ``module:function`` upstream)."""
    return {"executed": envelope.get("cmd"), "msg_id": envelope.get("msg_id")}


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def start_gateway(
    config: Path, port: int, timeout_s: float = 30.0, prefix: Sequence[str] = ()
) -> subprocess.Popen[bytes]:
    """Run ``antireplay serve --config CONFIG`` on loopback ``port`` (behind ``prefix``, a
    command such as ``nsenter ...``); return once it is healthy."""
    args = [*prefix, sys.executable, "-m", "antireplay", "serve", "--config", str(config)]
    args += ["--host", "127.0.0.1", "--port", str(port)]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:  # whatever ends the wait (a timeout, a signal) leaves no gateway behind
        _wait_healthy(proc, port, timeout_s)
    except BaseException:
        proc.kill()
        proc.wait()
        raise
    return proc


def _wait_healthy(proc: subprocess.Popen[bytes], port: int, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            err = proc.stderr.read().decode() if proc.stderr else ""
            raise RuntimeError(f"gateway exited early: {err[-2000:]}")
        try:
            if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            time.sleep(0.05)
    raise RuntimeError("gateway did not become healthy")


def stop_gateway(proc: subprocess.Popen[bytes]) -> str:
    """Graceful stop (uvicorn finishes in-flight requests); what the gateway said on stderr."""
    proc.terminate()
    _, err = proc.communicate(timeout=30)
    return err.decode(errors="replace") if err else ""


def write_demo_config(state: Path, **overrides: Any) -> Path:
    """A gateway config with a fresh Ed25519 operator key under ``state``."""
    write_key_pair(
        ed25519.Ed25519PrivateKey.generate(), state / "operator.key.pem", state / "operator.pub.pem"
    )
    config = {
        "store": f"sqlite:{state / 'state.db'}",
        "audit": str(state / "audit.db"),
        "upstream": "antireplay.cli.demo:robot",
        "keys": [
            {
                "kid": "operator",
                "owner": "operator",
                "alg": "ed25519",
                "public_keys": [str(state / "operator.pub.pem")],
                "scopes": ["control", "safety"],
            }
        ],
        **overrides,
    }
    path = state / "antireplay.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def load_operator_key(state: Path) -> ed25519.Ed25519PrivateKey:
    key = serialization.load_pem_private_key((state / "operator.key.pem").read_bytes(), None)
    assert isinstance(key, ed25519.Ed25519PrivateKey)
    return key


def command(key: ed25519.Ed25519PrivateKey, age_s: float = 0.0, **fields: Any) -> bytes:
    """A signed RCAN command stamped ``age_s`` seconds ago."""
    body = {
        "rcan": "3.2", "rcan_version": "3.2", "msg_id": str(uuid.uuid4()),
        "timestamp": round(time.time() - age_s, 6), "cmd": "move_forward",
        "target": "rcan://registry.rcan.dev/acme/arm/v2/unit-001",
        "params": {"distance_m": 0.5}, **fields,
    }  # fmt: skip
    return json.dumps(sign_envelope(body, "operator", "ed25519", key)).encode()


def answer(reply: httpx.Response) -> str:
    """How a step's HTTP reply reads in the table."""
    try:
        body = reply.json()
    except ValueError:
        return f"HTTP {reply.status_code}"
    if reply.status_code == 200:
        return "accepted" + (f", warning {body['warning']}" if body.get("warning") else "")
    return f"{body.get('code')} ({reply.status_code})"


def _entries(http: httpx.Client) -> int:
    """The gateway's replay-state entries, as its ``/metrics`` reports them."""
    found = re.search(
        r"^antireplay_cache_entries\{[^}]*\} ([0-9.e+]+)$", http.get("/metrics").text, re.M
    )
    return int(float(found.group(1))) if found else 0


@contextmanager
def _gateway(config: Path, port: int) -> Iterator[httpx.Client]:
    """A gateway process on ``port`` and a client for it, stopped on exit."""
    proc = start_gateway(config, port)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10) as http:
            wait_ready(http)
            yield http
    finally:
        stop_gateway(proc)


def wait_ready(http: httpx.Client, timeout_s: float = 30.0) -> None:
    """Wait for ``/readyz``, as a deployment would: a new state fences its first start for
    about ``skew_s`` ("fenced until T"), refusing every command stamped before T."""
    deadline = time.monotonic() + timeout_s
    while (reply := http.get("/readyz")).status_code != 200:
        if time.monotonic() > deadline:
            raise RuntimeError(f"gateway not ready: {reply.text}")
        time.sleep(0.1)


def run_gateway_demo(flood: int = 300) -> tuple[list[StepResult], ChainReport]:
    """Play operator and attacker against a real gateway; return the steps and audit check."""
    with tempfile.TemporaryDirectory(prefix="antireplay-demo-") as tmp:
        state = Path(tmp)
        config, port = write_demo_config(state), _free_port()
        key = load_operator_key(state)
        results: list[StepResult] = []

        def post(http: httpx.Client, raw: bytes) -> httpx.Response:
            return http.post("/v1/messages", content=raw, headers=JSON)

        def step(http: httpx.Client, name: str, expected: str, raw: bytes) -> None:
            results.append(StepResult(name, expected, answer(post(http, raw))))

        with _gateway(config, port) as http:
            first = command(key)
            step(http, "operator: move_forward", ACCEPTED, first)
            step(http, "attacker: exact replay", "REPLAY_DETECTED (409)", first)
            step(http, "attacker: capture from 40 s ago", "MESSAGE_STALE (408)", command(key, 40))
            genuine = json.loads(command(key))
            forged = {**genuine, "cmd": "arm_motors"}
            step(http, "attacker: forged msg with victim's msg_id", "SIGNATURE_INVALID (401)",
                 json.dumps(forged).encode())  # fmt: skip
            step(http, "operator: the genuine message", ACCEPTED, json.dumps(genuine).encode())
            before = _entries(http)
            garbage = [
                json.dumps({**json.loads(command(key)), "msg_id": f"flood-{i}", "cmd": "x"})
                for i in range(flood)
            ]
            refused = sum(post(http, g.encode()).status_code == 401 for g in garbage)
            results.append(StepResult(
                f"attacker: {flood} unique forged msgs (state rows {before} -> "
                f"{_entries(http)})", f"{flood} refused", f"{refused} refused",
            ))  # fmt: skip
            step(http, "attacker: replay after the flood", "REPLAY_DETECTED (409)", first)
            estop = command(key, type=6, safety_event="ESTOP", cmd="estop")
            step(http, "operator: ESTOP", ACCEPTED, estop)
            step(http, "network: duplicate fresh ESTOP", f"{ACCEPTED}, warning REPLAY_DETECTED",
                 estop)  # fmt: skip
            stale_estop = command(key, 11, type=6, safety_event="ESTOP", cmd="estop")
            step(http, "attacker: ESTOP from 11 s ago", "MESSAGE_STALE (408)", stale_estop)
        with _gateway(config, port) as http:  # the same gateway, restarted
            step(http, "attacker: replay after gateway restart", "REPLAY_DETECTED (409)", first)
        return results, verify(state / "audit.db")


JSON = {"content-type": "application/json"}
