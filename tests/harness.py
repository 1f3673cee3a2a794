"""The test harness: gateway processes, free ports and direct reads of a gateway's state.

The package keeps only what ``antireplay demo`` runs
(:func:`antireplay.cli.demo.start_gateway` and :func:`~antireplay.cli.demo.stop_gateway`);
what tests need beyond it (a restartable process that remembers what it said on
stderr, ports for other servers, the SQLite seen-set read directly, polling for an
event under a deadline, the rcan SDK's vocabulary over ours) lives here.
"""

from __future__ import annotations

import itertools
import json
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import pytest

from antireplay import ManualClock, MessageType, ReplayAttackError, ReplayCache, safety_class
from antireplay.cli.demo import start_gateway, stop_gateway
from antireplay.rcan.envelope import parse


def until(what: str, done: Callable[[], object], timeout: float = 30.0) -> None:
    """Poll ``done`` until it is truthy (an event the test brings about, under a deadline,
    never a timing guess); fail naming ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not done():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.005)


def free_port() -> int:
    """A loopback TCP port nothing listens on now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class GatewayProcess:
    """``antireplay serve`` as a real subprocess on loopback, restartable on its port."""

    config: Path
    port: int = field(default_factory=free_port)
    proc: subprocess.Popen[bytes] | None = None
    stderr_text: str | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout_s: float = 30.0) -> None:
        self.proc = start_gateway(self.config, self.port, timeout_s)

    def stop(self) -> None:
        """Graceful stop (uvicorn finishes in-flight requests); keeps what it said on stderr."""
        if self.proc is not None:
            self.stderr_text = stop_gateway(self.proc)
            self.proc = None


def state_rows(state: Path) -> int:
    """Rows in the seen-set of the SQLite store under ``state`` (read-only)."""
    db = sqlite3.connect(f"file:{state / 'state.db'}?mode=ro", uri=True)
    try:
        return int(db.execute("SELECT count(*) FROM seen").fetchone()[0])
    finally:
        db.close()


@dataclass(frozen=True)
class Request:
    """One request a :func:`recording_upstream` received: its headers (lower-cased) and body."""

    headers: dict[str, str]
    body: bytes


@contextmanager
def recording_upstream(
    before_answer: Callable[[], object] | None = None,
) -> Iterator[tuple[str, list[Request]]]:
    """A robot API on loopback (its URL) that keeps every POST it is handed and answers ``{}``
    (after ``before_answer()`` returns: a test can hold requests there)."""
    received: list[Request] = []

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            body = self.rfile.read(int(self.headers["content-length"]))
            received.append(Request({k.lower(): v for k, v in self.headers.items()}, body))
            if before_answer is not None:
                before_answer()
            self.send_response(200)
            self.send_header("content-type", "application/json")
            self.send_header("content-length", "2")
            self.end_headers()
            self.wfile.write(b"{}")

        def log_message(self, *args: Any) -> None:
            """Quiet."""

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_port}/", received
    finally:
        server.shutdown()
        server.server_close()


@contextmanager
def metrics_router(tmp_path: Path, host: str | None = None) -> Iterator[int]:
    """A real ``antireplay mavlink-router`` (UDP in and out, memory store) serving its metrics
    on a free port (on ``host`` if given): yields that port once it says it runs."""
    key = tmp_path / "link.key"
    key.write_bytes(bytes(range(32)))
    port = free_port()
    args = [
        sys.executable, "-m", "antireplay", "mavlink-router", "--listen",
        f"udp:127.0.0.1:{free_port()}", "--forward", f"udp:127.0.0.1:{free_port()}",
        "--key-file", str(key), "--store", "memory", "--audit", str(tmp_path / "router.db"),
        "--metrics-port", str(port), *(["--metrics-host", host] if host else []),
    ]  # fmt: skip
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert proc.stdout is not None
        assert b"mavlink-router" in proc.stdout.readline(), proc.stderr
        yield port
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def pq_keys(directory: Path) -> None:
    """The post-quantum link's keys as ``antireplay keygen`` writes them: ``gcs.key.pem`` /
    ``gcs.pub.pem`` (ML-DSA-87), ``vehicle.key.pem`` / ``vehicle.pub.pem`` (ML-KEM-1024)."""
    from cryptography.hazmat.primitives import serialization as ser  # noqa: PLC0415
    from cryptography.hazmat.primitives.asymmetric import mldsa, mlkem  # noqa: PLC0415

    keys: dict[str, Any] = {
        "gcs": mldsa.MLDSA87PrivateKey.generate(),
        "vehicle": mlkem.MLKEM1024PrivateKey.generate(),
    }
    for name, key in keys.items():
        (directory / f"{name}.key.pem").write_bytes(
            key.private_bytes(ser.Encoding.PEM, ser.PrivateFormat.PKCS8, ser.NoEncryption())
        )
        (directory / f"{name}.pub.pem").write_bytes(
            key.public_key().public_bytes(ser.Encoding.PEM, ser.PublicFormat.SubjectPublicKeyInfo)
        )


@contextmanager
def metrics_pq(tmp_path: Path) -> Iterator[int]:
    """A real ``antireplay mavlink-pq ground`` (its air path leads nowhere) serving its
    metrics on a free port: yields that port once it says it runs."""
    pq_keys(tmp_path)
    port = free_port()
    args = [
        sys.executable, "-m", "antireplay", "mavlink-pq", "ground",
        "--local", f"udpin:127.0.0.1:{free_port()}", "--air", f"udpout:127.0.0.1:{free_port()}",
        "--signing-key", str(tmp_path / "gcs.key.pem"),
        "--vehicle-key", str(tmp_path / "vehicle.pub.pem"),
        "--audit", str(tmp_path / "pq.db"), "--metrics-port", str(port),
    ]  # fmt: skip
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        said = [proc.stderr.readline()]
        while not said[-1].startswith("mavlink-pq ground") and said[-1]:
            said.append(proc.stderr.readline())
        assert said[-1], said
        yield port
    finally:
        proc.terminate()
        proc.wait(timeout=30)


#: Where the SDK's conformance cases run: a fixed wall time on a manual clock.
SDK_NOW = 1_800_000_000.0


class SdkReplayAdapter:
    """The rcan SDK's receive-side names over antireplay's public API, so its own test
    cases can be restated against ours: ``check_and_record`` and ``validate_replay``
    (``rcan.replay``), ``is_safety_message`` and ``validate_safety_message``
    (``rcan.safety``).  Answers keep the SDK's shape: ``(allowed, reason)`` (the reason of
    an admitted message is its warning, ``""`` for none) and a list of errors.

    ``up_s``: how long the in-memory cache has been running at ``SDK_NOW``: the SDK's
    cases assume a running receiver, while ours refuses whatever is stamped before its
    start plus its skew (the restart fence; the conformance table's one case with
    ``up_s=0`` states it)."""

    def __init__(
        self, window_s: float = 30.0, max_size: int = 10_000, *, up_s: float = 60.0
    ) -> None:
        self.clock = ManualClock(SDK_NOW - up_s)
        self.cache = ReplayCache(window_s, max_size, clock=self.clock)
        self.clock.step_wall(up_s)

    @property
    def window_s(self) -> float:
        return self.cache.window_s

    def __len__(self) -> int:
        return len(self.cache)

    def check_and_record(
        self, msg_id: object, timestamp: object, is_safety: bool = False
    ) -> tuple[bool, str]:
        kind = MessageType.SAFETY if is_safety else MessageType.COMMAND
        return self._record(msg_id, timestamp, kind, None)

    def validate_replay(self, msg: dict[str, Any]) -> tuple[bool, str]:
        """The SDK's ``validate_replay(msg, cache)``: ``msg`` (``RCANMessage.to_dict()``)
        as our receiver classes it (envelope, then :func:`safety_class`)."""
        try:
            env = parse(json.dumps(msg).encode())
        except ReplayAttackError as exc:
            return False, str(exc)
        kind, event = safety_class(env)
        return self._record(env.msg_id, env.seconds, kind, event)

    def is_safety_message(self, msg: dict[str, Any]) -> bool:
        classed = self._classify(msg)
        return isinstance(classed, tuple) and classed[0] == MessageType.SAFETY

    def validate_safety_message(self, msg: dict[str, Any]) -> list[str]:
        classed = self._classify(msg)
        if isinstance(classed, str):
            return [classed]
        if classed[0] != MessageType.SAFETY:
            return [f"message_type {classed[0]} is not SAFETY"]
        return []

    def _classify(self, msg: dict[str, Any]) -> tuple[int, str | None] | str:
        """An ``rcan.safety`` dict in our envelope's names (``message_type`` -> ``type``,
        ``message_id`` -> ``msg_id``, ``ruri`` -> ``target``, the event as ``cmd``, the
        reason as a parameter), classed by :func:`safety_class`; a refusal's reason."""
        names = {"message_type": "type", "message_id": "msg_id", "ruri": "target"}
        ours = {names.get(k, k): v for k, v in msg.items() if k != "reason"}
        ours.setdefault("cmd", msg.get("safety_event", ""))
        if "reason" in msg:
            ours["params"] = {"reason": msg["reason"]}
        try:
            return safety_class(parse(json.dumps(ours).encode()))
        except ReplayAttackError as exc:
            return str(exc)

    def _record(
        self, msg_id: object, timestamp: object, kind: int, event: str | None
    ) -> tuple[bool, str]:
        """Check (records nothing), then commit: the two phases with nothing to verify."""
        try:
            self.cache.check(msg_id, timestamp, kind, event)
            verdict = self.cache.commit(msg_id, timestamp, kind, event)
        except ReplayAttackError as exc:
            return False, str(exc) + (f" ({exc.detail})" if exc.detail else "")
        return True, verdict.warning or ""


def dds_writer_process(
    domain_id: int, psk: bytes, topic: str, *, period_s: float, max_forward_s: float
) -> subprocess.Popen[str]:
    """A second process with one sealed DDS writer (loopback domain ``domain_id``) that
    writes ``#n`` every ``period_s`` and prints each sample's sealed hex (a capture)."""
    args = [str(domain_id), psk.hex(), topic, str(period_s), str(max_forward_s)]
    code = "from tests.harness import dds_writer_main; dds_writer_main()"
    return subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip


def dds_writer_main() -> None:
    """The body of :func:`dds_writer_process` (runs until killed)."""
    from antireplay.dds.domain import join_domain  # noqa: PLC0415 - the child's own imports
    from antireplay.dds.topics import SealedWriter  # noqa: PLC0415

    domain_id, psk, topic, period_s, forward_s = sys.argv[1:6]
    writer = SealedWriter(join_domain(int(domain_id)), topic, bytes.fromhex(psk),
                          max_forward_s=float(forward_s))  # fmt: skip
    for n in itertools.count():
        sample = writer.write(f"#{n}".encode(), instance="arm")
        print(bytes(sample.sealed).hex(), flush=True)
        time.sleep(float(period_s))
