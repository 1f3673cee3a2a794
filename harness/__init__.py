"""The process harness: what the tests and the benchmarks share (fixtures are in
``tests/conftest.py``).  It imports neither ``tests`` nor ``benchmarks``, and neither
imports the other; it is not part of the installed package.

The package keeps only what ``antireplay demo`` runs
(:func:`antireplay.cli.demo.start_gateway` and :func:`~antireplay.cli.demo.stop_gateway`);
what tests need beyond it lives here: polling for an event under a deadline, free ports,
gateway processes and what is said to them, threads released together, helpers killed
mid-stride, caches and receivers started before the test's "now", and the rcan SDK's
vocabulary over ours.  Submodules: :mod:`~harness.envelopes` (signed RCAN
messages), :mod:`~harness.asgi` (a gateway in process), :mod:`~harness.audit`
(trails), :mod:`~harness.stores` (Redis replicas), :mod:`~harness.mavlink_frames`
and :mod:`~harness.mavproxy` (MAVLink links), :mod:`~harness.redis_server`
(a real Redis), :mod:`~harness.radio` and :mod:`~harness.pq_radio` (a lossy radio and
the PQ ends over it), :mod:`~harness.workers` (subprocesses for kill -9 tests).
"""

from __future__ import annotations

import itertools
import json
import os
import random
import re
import signal
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
from typing import Any, TypeVar

import httpx
import pytest
from click.testing import Result

from antireplay import ManualClock, MessageType, ReplayAttackError, ReplayCache, safety_class
from antireplay.cli.demo import JSON, command, load_operator_key, start_gateway, stop_gateway
from antireplay.rcan.auth import sign_envelope
from antireplay.rcan.envelope import parse
from antireplay.rcan.receive import Receiver


def until(what: str, done: Callable[[], object], timeout: float = 30.0) -> None:
    """Poll ``done`` until it is truthy (an event the test brings about, under a deadline,
    never a timing guess); fail naming ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not done():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.005)


def _below_ephemeral() -> range:
    """Ports the kernel never picks on its own: below its ephemeral range, from which it
    draws the source port of every client socket (a udpout link, a connection) and
    every bind to port 0, so a port handed out here cannot be taken by one meanwhile."""
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    return range(max(1024, low - 12000), low)


_PORTS = _below_ephemeral()
#: Ports this process handed out: never twice, though the first may not be bound yet.
_HANDED: set[int] = set()


def free_port() -> int:
    """A loopback port nothing is bound to now, for TCP and for UDP alike, outside the
    kernel's ephemeral range and never handed out twice by this process."""
    for _ in range(1000):
        port = random.choice(_PORTS)
        if port in _HANDED:
            continue
        try:
            for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
                with socket.socket(socket.AF_INET, kind) as sock:
                    sock.bind(("127.0.0.1", port))
        except OSError:
            continue
        _HANDED.add(port)
        return port
    raise RuntimeError(f"no free loopback port in {_PORTS}")


def free_udp_port() -> int:
    """A loopback UDP port nothing is bound to now (:func:`free_port`: it checks both)."""
    return free_port()


@dataclass
class GatewayProcess:
    """``antireplay serve`` as a real subprocess on loopback, restartable on its port."""

    config: Path
    port: int = field(default_factory=free_port)
    proc: subprocess.Popen[bytes] | None = None
    stderr_text: str | None = None
    #: A command the gateway runs behind (``nsenter`` into a small filesystem's namespace).
    prefix: tuple[str, ...] = ()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout_s: float = 30.0, *, past_fence: bool = True) -> None:
        """Start and wait until healthy; ``past_fence``: and until ``/readyz`` no longer
        says "fenced until" (a state with no history fences its first start, as a memory
        store fences every start: about ``skew_s``), so what the test sends is judged by
        the rule it tests, not by that fence (which has its own tests)."""
        self.proc = start_gateway(self.config, self.port, timeout_s, self.prefix)
        if past_fence:
            wait_past_fence(self.url, timeout_s)

    def stop(self) -> None:
        """Graceful stop (uvicorn finishes in-flight requests); keeps what it said on stderr."""
        if self.proc is not None:
            self.stderr_text = stop_gateway(self.proc)
            self.proc = None


def antireplay(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``antireplay ARGS`` as a user runs it: a process of its own, its output as text."""
    return subprocess.run(
        [sys.executable, "-m", "antireplay", *args],
        cwd=cwd, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip


def child_pids(pid: int) -> list[int]:
    """The processes ``pid`` started that are still running (Linux ``/proc``)."""
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(c) for c in (task / "children").read_text().split()]
        except OSError:  # the task ended meanwhile
            continue
    return found


def wait_past_fence(url: str, timeout_s: float = 30.0) -> None:
    """Poll ``url``'s ``/readyz`` until its reason is no longer a fence ("fenced until T"):
    ready, or not ready for another reason the test is about."""

    def past() -> bool:
        reply = httpx.get(f"{url}/readyz", timeout=10)
        return reply.status_code == 200 or "fenced until" not in reply.text

    until("the start's fence to pass", past, timeout_s)


@contextmanager
def serving(config: Path) -> Iterator[GatewayProcess]:
    """A started :class:`GatewayProcess` on ``config``, stopped afterwards."""
    process = GatewayProcess(config)
    process.start()
    try:
        yield process
    finally:
        process.stop()


def post(to: GatewayProcess | httpx.Client, raw: bytes, **headers: str) -> httpx.Response:
    """POST ``raw`` to ``/v1/messages`` of a gateway process or through a client bound to one."""
    sent = {**JSON, **headers}
    if isinstance(to, GatewayProcess):
        return httpx.post(f"{to.url}/v1/messages", content=raw, headers=sent, timeout=10)
    return to.post("/v1/messages", content=raw, headers=sent)


def signed_by(key: Any, kid: str, **fields: Any) -> bytes:
    """A fresh demo command (:func:`~antireplay.cli.demo.command`) signed by Ed25519 ``key``
    under ``kid`` (a second key of the operator: a rotation)."""
    body = {k: v for k, v in json.loads(command(key, **fields)).items() if k != "sig"}
    return json.dumps(sign_envelope(body, kid, "ed25519", key)).encode()


def metric(of: GatewayProcess | httpx.Client, name: str, labels: str = "") -> float:
    """One sample of a gateway's ``/metrics`` (0 when absent)."""
    if isinstance(of, GatewayProcess):
        text = httpx.get(f"{of.url}/metrics", timeout=10).text
    else:
        text = of.get("/metrics").text
    found = re.search(rf"^{re.escape(name + labels)} ([0-9.e+]+)$", text, re.MULTILINE)
    return float(found.group(1)) if found else 0.0


def post_after_cut(gateway: GatewayProcess, raw: bytes) -> httpx.Response:
    """The first request after Redis went away may meet the pooled connection it cut
    (503 STATE_UNAVAILABLE, fail closed); exactly that, once, is tolerated."""
    reply = post(gateway, raw)
    if reply.status_code == 503:
        assert reply.json()["code"] == "STATE_UNAVAILABLE", reply.text
        reply = post(gateway, raw)
    assert reply.status_code != 503, reply.text
    return reply


def accepted_fresh(gateway: GatewayProcess, state: Path, timeout_s: float = 20.0) -> bytes:
    """Send fresh commands until one is accepted (a fence lasts about the gateway's skew_s)."""
    key = load_operator_key(state)
    deadline = time.monotonic() + timeout_s
    refusals: list[str] = []
    while time.monotonic() < deadline:
        raw = command(key)
        reply = post_after_cut(gateway, raw)
        if reply.status_code == 200:
            return raw
        body = reply.json()
        assert (reply.status_code, body.get("detail")) == (408, "restart_fence"), reply.text
        refusals.append(reply.text)
        time.sleep(0.05)
    pytest.fail(f"no fresh message was accepted within {timeout_s}s: {refusals[-3:]}")


def reencoded(raw: bytes) -> bytes:
    """The same signed message in other bytes (gets past a gateway's memo of accepted bodies)."""
    return json.dumps(json.loads(raw), indent=1, sort_keys=True).encode()


def data_losses(gateway: GatewayProcess) -> float:
    return metric(gateway, "antireplay_state_data_loss_total", '{backend="redis"}')


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
    """A real ``antireplay mavlink-router`` (UDP in and out, a SQLite state with history, so
    no first start's fence) serving its metrics on a free port (on ``host`` if given):
    yields that port once it says it runs."""
    from harness.stores import aged_state  # noqa: PLC0415 - harness.stores imports this module

    state = aged_state(tmp_path / "router-state.db")
    key = tmp_path / "link.key"
    key.write_bytes(bytes(range(32)))
    port = free_port()
    args = [
        sys.executable, "-m", "antireplay", "mavlink-router", "--listen",
        f"udp:127.0.0.1:{free_udp_port()}", "--forward", f"udp:127.0.0.1:{free_udp_port()}",
        "--key-file", str(key), "--store", f"sqlite:{state}",
        "--audit", str(tmp_path / "router.db"), "--metrics-port", str(port),
        *(["--metrics-host", host] if host else []),
    ]  # fmt: skip
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert proc.stdout is not None
        assert b"mavlink-router" in proc.stdout.readline(), proc.stderr
        yield port
    finally:
        proc.terminate()
        proc.wait(timeout=30)


ROOT = Path(__file__).resolve().parents[1]


T = TypeVar("T")


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
        "--local", f"udpin:127.0.0.1:{free_udp_port()}",
        "--air", f"udpout:127.0.0.1:{free_udp_port()}",
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


def fresh_cache(*args: Any, **kwargs: Any) -> ReplayCache:
    """A ReplayCache whose ManualClock is moved past its restart fence (start + skew + window).

    A new in-memory cache refuses anything stamped at or before its start plus skew
    (it cannot know what a previous process accepted); tests that are not about
    that fence start just after it.
    """
    cache = ReplayCache(*args, **kwargs)
    clock = kwargs.get("clock", args[3] if len(args) > 3 else None)
    if isinstance(clock, ManualClock):
        clock.advance(cache.policy.window_s + cache.policy.skew_s + 1)
    return cache


#: How long before a test's "now" its receiver's in-memory store started (> window + skew).
STARTED_BEFORE_S = 400.0


def fresh_receiver(*args: Any, **kwargs: Any) -> Receiver:
    """A Receiver whose in-memory store started long enough ago that its restart fence
    refuses nothing the test sends (the fence has its own tests)."""
    clock = kwargs.get("clock", args[4] if len(args) > 4 else None)
    if not isinstance(clock, ManualClock):
        return Receiver(*args, **kwargs)
    clock.step_wall(-STARTED_BEFORE_S)
    try:
        return Receiver(*args, **kwargs)
    finally:
        clock.step_wall(STARTED_BEFORE_S)


def started_before(clock: ManualClock, build: Callable[[], T]) -> T:
    """``build()`` on ``clock`` stepped ``STARTED_BEFORE_S`` back: an epoch verifier or DDS
    reader whose in-memory store (and start fence) began long before the test's "now"
    (the fence has its own tests)."""
    clock.step_wall(-STARTED_BEFORE_S)
    try:
        return build()
    finally:
        clock.step_wall(STARTED_BEFORE_S)


def run_threads(threads_n: int, work: Callable[[int], object]) -> None:
    """Run ``work(index)`` in ``threads_n`` real threads released together by a barrier."""
    barrier = threading.Barrier(threads_n)

    def worker(index: int) -> None:
        barrier.wait()
        work(index)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(threads_n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def race(threads_n: int, action: Callable[[], object]) -> tuple[int, int]:
    """Start ``threads_n`` threads behind a barrier; count successes and typed rejections."""
    results: list[bool] = []
    lock = threading.Lock()

    def attempt(_: int) -> None:
        try:
            action()
            ok = True
        except ReplayAttackError:
            ok = False
        with lock:
            results.append(ok)

    run_threads(threads_n, attempt)
    return results.count(True), results.count(False)


def run_and_kill(args: list[str], lines: int, rng: random.Random) -> list[str]:
    """Start a Python helper, read ``lines`` lines of output, then SIGKILL it mid-stride."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT / "src"), str(ROOT)]))
    proc = subprocess.Popen(
        [sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True
    )
    assert proc.stdout is not None
    out: list[str] = []
    for _ in range(lines):
        line = proc.stdout.readline()
        if not line:
            break
        out.append(line.strip())
    if rng.random() < 0.5:  # sometimes let it run a little further before the kill
        for _ in range(rng.randint(1, 50)):
            line = proc.stdout.readline()
            if line:
                out.append(line.strip())
    proc.send_signal(signal.SIGKILL)
    rest, err = proc.communicate(timeout=30)
    out.extend(x for x in rest.split("\n") if x.strip())
    if proc.returncode != -signal.SIGKILL:
        raise AssertionError(f"helper exited {proc.returncode}: {err}")
    return out


def kill9_runs(args: list[str], rounds: int, max_lines: int, seed: int) -> list[list[str]]:
    """Run a helper ``rounds`` times on the same state, SIGKILLing each at a random moment."""
    rng = random.Random(seed)
    return [run_and_kill(args, rng.randint(1, max_lines), rng) for _ in range(rounds)]


def assert_never_reused(runs: list[list[str]], what: str) -> None:
    """Each run starts above everything earlier runs printed, and no value ever repeats."""
    seen: list[int] = []
    for lines in runs:
        values = [int(x) for x in lines]
        assert values, "worker produced nothing"
        if seen:
            assert values[0] > max(seen), f"a restarted {what} reused a value"
        seen.extend(values)
    assert len(seen) == len(set(seen))


def one_line_error(result: Result, *needles: str) -> str:
    """The mistake is one unwrapped stderr line naming the input; nothing on stdout."""
    assert result.exit_code == 2, (result.exit_code, result.output)
    assert isinstance(result.exception, SystemExit), result.exception
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("antireplay: error: ")
    assert "Traceback" not in result.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


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


class Reaper:
    """The child processes a test started, killed and reaped when it ends, passed or failed
    (use it from an autouse fixture): a hung or failed test never leaves a child running."""

    def __init__(self) -> None:
        self._started: list[subprocess.Popen[str]] = []

    def __call__(self, process: subprocess.Popen[str]) -> subprocess.Popen[str]:
        self._started.append(process)
        return process

    def reap(self) -> None:
        """Kill every child still running, then collect its exit and pipes (bounded)."""
        while self._started:
            process = self._started.pop()
            if process.poll() is None:
                process.kill()
            process.communicate(timeout=30)


def dds_writer_process(
    domain_id: int, psk: bytes, topic: str, *, period_s: float, max_forward_s: float
) -> subprocess.Popen[str]:
    """A second process with one sealed DDS writer (loopback domain ``domain_id``) that
    writes ``#n`` every ``period_s`` and prints each sample's sealed hex (a capture)."""
    args = [str(domain_id), psk.hex(), topic, str(period_s), str(max_forward_s)]
    code = "from harness import dds_writer_main; dds_writer_main()"
    return subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip


def dds_junk_process(domain_id: int, topic: str) -> subprocess.Popen[str]:
    """A process without the fleet key flooding the challenge channel about ``topic`` with
    challenges and answers sealed under random keys, on sender instances of its own
    (``antireplay/ping``); it prints ``flooding`` once it has written its first thousand."""
    code = "from harness import dds_junk_main; dds_junk_main()"
    return subprocess.Popen([sys.executable, "-c", code, str(domain_id), topic],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip


#: Sender instances one junk process cycles through: its writer's instance table (keep-last
#: per instance) stays bounded however long it floods.
JUNK_SENDERS = 256


def dds_junk_main() -> None:
    """The body of :func:`dds_junk_process` (runs until killed).  A writer only: no reader,
    so nothing in this process grows with the traffic it meets (an unfiltered reader here
    once held every other junk process's instances, 11.8 GB)."""
    from cyclonedds.pub import DataWriter  # noqa: PLC0415 - the child's own imports
    from cyclonedds.topic import Topic  # noqa: PLC0415

    from antireplay.dds.challenge import PING_TOPIC, ping_instance, ping_qos  # noqa: PLC0415
    from antireplay.dds.domain import join_domain  # noqa: PLC0415
    from antireplay.dds.wire import SealedSample  # noqa: PLC0415
    from antireplay.epochs import Kind, derive_key  # noqa: PLC0415
    from antireplay.epochs.policy import seal  # noqa: PLC0415

    domain_id, topic = int(sys.argv[1]), sys.argv[2]
    participant, qos = join_domain(domain_id), ping_qos()
    writer = DataWriter(participant, Topic(participant, PING_TOPIC, SealedSample, qos=qos), qos=qos)
    key = derive_key(os.urandom(32), Kind.PING)
    senders = [os.urandom(8) for _ in range(JUNK_SENDERS)]
    for n in itertools.count():
        kind = Kind.CHALLENGE if n % 2 else Kind.ANSWER
        prefix = senders[n % JUNK_SENDERS]
        sealed = seal(key, kind, prefix, time.time_ns(), os.urandom(16))
        writer.write(SealedSample(instance=ping_instance(topic, prefix), sealed=sealed))
        if n == 1000:
            print("flooding", flush=True)


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
