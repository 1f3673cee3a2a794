"""The gateway users run, under a concurrent load generator, beside a bare Starlette app.

Run: ``python -m benchmarks.bench_gateway`` (needs ``wrk``: ``apt-get install -y wrk``).

What is measured, and why this way:

* The gateway is ``antireplay serve --state-dir DIR`` on its embedded default
  (SQLite seen-set and audit trail on disk, fsync on commit): the durable
  configuration users get.  The baseline is a Starlette app on the same uvicorn,
  started with the same options, that only parses the JSON body and answers 200.
* The load comes from wrk, a C load generator in its own process (keep-alive,
  loopback, one wrk thread), at 1 and 32 connections.  Python clients become the
  bottleneck long before the servers do, which hides what concurrency costs.
* Fresh commands: every request carries its own signed Ed25519 envelope.  They are
  signed ahead of each run into a file that a Lua ``request()`` hook walks through
  (enough for the run: a wrapped list would be replays, and the run fails then).
  Replays: one captured command, accepted once, sent again and again (409).
* Rounds are interleaved (bare, gateway, bare, ... for every case) and the
  figures are medians over rounds, so a noisy neighbour hits both sides alike.
  ``CPU ms/req`` is the server process's user + system CPU (all threads, from
  /proc) per answered request: the figure a busy shared machine skews least.
* Fsyncs of a replay flood: 10,000 replays at 32 connections against a gateway
  started under ``strace -f --seccomp-bpf`` (only fsync/fdatasync are trapped, so
  the tracing costs little), counted between the flood's start and end, and the
  audit rows the flood wrote are counted in the audit database (every rejection
  must be audited).  ``/metrics`` is also read before and after for any
  group-commit batch counter it exposes.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import signal
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import httpx
import uvicorn
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ed25519
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route
from tests.harness import free_port

from antireplay.rcan.auth import sign_envelope
from antireplay.wiring import DEMO_KID

ROUNDS = 3
SECONDS = 3
CONNECTIONS = (1, 32)
FLOOD = 10_000
#: Signed envelopes per fresh run: more than the fastest server answers in SECONDS.
FRESH_PER_RUN = 15_000
TARGETS = {"fresh": 0.5, "replay": 0.8}
P99_TARGET_MS = 50.0

WRK_SCRIPT = """
local bodies = {}
local i = 0
local limit = 0
local seen = 0
local headers = {["Content-Type"] = "application/json"}

function init(args)
  for line in io.lines(args[1]) do bodies[#bodies + 1] = line end
  limit = tonumber(args[2] or "0")
end

function request()
  i = i + 1
  if i > #bodies then i = 1 end
  return wrk.format("POST", "/v1/messages", headers, bodies[i])
end

if os.getenv("WRK_STOP_AFTER") then
  function response(status, hdrs, body)
    seen = seen + 1
    if limit > 0 and seen >= limit then wrk.thread:stop() end
  end
end

function done(summary, latency, requests)
  local e = summary.errors
  io.write(string.format(
    'WRK {"requests": %d, "duration_us": %d, "p50_us": %d, "p99_us": %d, '
    .. '"status_errors": %d, "socket_errors": %d}\\n',
    summary.requests, summary.duration, latency:percentile(50), latency:percentile(99),
    e.status, e.connect + e.read + e.write + e.timeout))
end
"""


def bare_app() -> Starlette:
    async def messages(request: Request) -> Response:
        body = json.loads(await request.body())
        return JSONResponse({"accepted": True, "msg_id": body.get("msg_id")})

    return Starlette(routes=[Route("/v1/messages", messages, methods=["POST"])])


@dataclass(frozen=True)
class Run:
    """One wrk run: throughput, latency, and how many answers were not 2xx."""

    rps: float
    p50_ms: float
    p99_ms: float
    requests: int
    non_2xx: int
    #: Server CPU (all threads, user + system) per request: what a busy neighbour cannot skew.
    cpu_ms: float


def cpu_seconds(pid: int) -> float:
    """User + system CPU of process ``pid`` so far (every thread), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wrk(  # noqa: PLR0917 - the load and its target
    url: str, pid: int, script: Path, bodies: Path, connections: int, seconds: int, stop: int = 0
) -> Run:
    cpu = cpu_seconds(pid)
    args = ["wrk", "-t1", f"-c{connections}", f"-d{seconds}s", "-s", str(script), url]
    env = {**os.environ, **({"WRK_STOP_AFTER": "1"} if stop else {})}
    out = subprocess.run(
        [*args, "--", str(bodies), str(stop)], capture_output=True, text=True, env=env, check=True
    ).stdout
    line = next((ln for ln in out.splitlines() if ln.startswith("WRK ")), None)
    if line is None:
        raise SystemExit(f"wrk printed no summary:\n{out}")
    cpu = cpu_seconds(pid) - cpu
    data = json.loads(line[4:])
    if data["socket_errors"]:
        raise SystemExit(f"{url}: {data['socket_errors']} socket errors under wrk")
    seconds_run = data["duration_us"] / 1e6
    return Run(
        data["requests"] / seconds_run,
        data["p50_us"] / 1e3,
        data["p99_us"] / 1e3,
        data["requests"],
        data["status_errors"],
        cpu * 1e3 / max(data["requests"], 1),
    )


@dataclass(frozen=True)
class Server:
    """A server under test: where it listens and the process whose CPU is counted."""

    url: str
    pid: int


def wait_healthy(url: str, proc: subprocess.Popen[bytes], path: str) -> None:
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"{url}: server exited with {proc.returncode}")
        try:
            httpx.request("GET" if path else "POST", url + (path or "/v1/messages"), content=b"{}")
            return
        except httpx.HTTPError:
            time.sleep(0.05)
    raise SystemExit(f"{url}: server did not start")


def serve_gateway(
    state: Path, port: int, prefix: list[str] | None = None
) -> subprocess.Popen[bytes]:
    """``antireplay serve`` on the embedded default, as users start it."""
    args = [sys.executable, "-m", "antireplay", "serve", "--state-dir", str(state)]
    proc = subprocess.Popen([*(prefix or []), *args, "--port", str(port)])
    wait_healthy(f"http://127.0.0.1:{port}", proc, "/healthz")
    return proc


def stop(proc: subprocess.Popen[bytes]) -> None:
    proc.terminate()
    proc.wait(timeout=30)


def signer(state: Path) -> ed25519.Ed25519PrivateKey:
    key = serialization.load_pem_private_key((state / f"{DEMO_KID}.key.pem").read_bytes(), None)
    assert isinstance(key, ed25519.Ed25519PrivateKey)
    return key


def envelope(key: ed25519.Ed25519PrivateKey, age_s: float = 0.0) -> str:
    """One signed RCAN command for the embedded default's demo operator key, on one line,
    stamped ``age_s`` seconds ago."""
    body = {
        "rcan": "3.2", "rcan_version": "3.2", "msg_id": str(uuid.uuid4()),
        "timestamp": round(time.time() - age_s, 6), "cmd": "move_forward",
        "target": "rcan://registry.rcan.dev/acme/arm/v2/unit-001",
        "params": {"distance_m": 0.5},
    }  # fmt: skip
    return json.dumps(sign_envelope(body, DEMO_KID, "ed25519", key))


def write_lines(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def audited(audit_db: Path, code: str) -> int:
    db = sqlite3.connect(f"file:{audit_db}?mode=ro", uri=True)
    try:
        return int(db.execute("SELECT count(*) FROM audit WHERE code = ?", (code,)).fetchone()[0])
    finally:
        db.close()


def batch_counters(url: str) -> dict[str, float]:
    """Every ``/metrics`` sample whose name mentions a batch (group commit), by name."""
    text = httpx.get(url + "/metrics").text
    samples = (ln.rsplit(" ", 1) for ln in text.splitlines() if ln and not ln.startswith("#"))
    return {name: float(value) for name, value in samples if "batch" in name}


def measure(
    work: Path, bare: Server, gateway: Server, key: ed25519.Ed25519PrivateKey
) -> dict[tuple[str, int, str], list[Run]]:
    """Interleaved rounds of every (path, connections, server) case."""
    servers = (bare, gateway)
    script = write_lines(work / "bodies.lua", [WRK_SCRIPT])
    captured = envelope(key)
    first = httpx.post(gateway.url + "/v1/messages", content=captured, headers=_JSON)
    if first.status_code != 200:
        raise SystemExit(f"gateway refused the command to be replayed: {first.text}")
    replay = write_lines(work / "replay.txt", [captured])
    for target in servers:  # warm-up: imports, caches, connection setup
        wrk(target.url, target.pid, script, replay, 32, 1)
    runs: dict[tuple[str, int, str], list[Run]] = {}
    for _ in range(ROUNDS):
        for connections in CONNECTIONS:
            fresh = write_lines(work / "fresh.txt", [envelope(key) for _ in range(FRESH_PER_RUN)])
            for path, bodies in (("fresh", fresh), ("replay", replay)):
                for server, target in zip(("bare", "gateway"), servers, strict=True):
                    run = wrk(target.url, target.pid, script, bodies, connections, SECONDS)
                    expected_errors = (
                        run.requests if server == "gateway" and path == "replay" else 0
                    )
                    if run.non_2xx != expected_errors:
                        raise SystemExit(
                            f"{server} {path} c={connections}: {run.non_2xx} of {run.requests}"
                            f" answers were not 2xx, {expected_errors} expected"
                            + (" (raise FRESH_PER_RUN?)" if path == "fresh" else "")
                        )
                    runs.setdefault((path, connections, server), []).append(run)
    return runs


def report(runs: dict[tuple[str, int, str], list[Run]]) -> float:
    """Print medians and ratios; returns the replay rate at 32 connections."""
    print(f"wrk, 1 thread, keep-alive, loopback, {SECONDS} s per run, median of {ROUNDS} rounds")
    http = "httptools" if importlib.util.find_spec("httptools") else "h11"
    loop = "uvloop" if importlib.util.find_spec("uvloop") else "asyncio"
    print(f"uvicorn {uvicorn.__version__} picks: http={http}, loop={loop} (both servers)")
    head = f"{'case':<14} {'server':<8} {'req/s':>7} {'p50 ms':>7} {'p99 ms':>7} {'ratio':>6}"
    head += f" {'CPU ms/req':>10}"
    print(head)
    replay_rate = 0.0
    for path in ("fresh", "replay"):
        for connections in CONNECTIONS:
            bare = runs[(path, connections, "bare")]
            base = statistics.median(r.rps for r in bare)
            for server in ("bare", "gateway"):
                rs = runs[(path, connections, server)]
                rps = statistics.median(r.rps for r in rs)
                p50 = statistics.median(r.p50_ms for r in rs)
                p99 = statistics.median(r.p99_ms for r in rs)
                cpu = statistics.median(r.cpu_ms for r in rs)
                verdict = ""
                if server == "gateway" and connections == max(CONNECTIONS):
                    ok = rps / base >= TARGETS[path] and p99 <= P99_TARGET_MS
                    verdict = f"  target >= {TARGETS[path]}x, p99 <= {P99_TARGET_MS:.0f} ms: "
                    verdict += "met" if ok else "MISSED"
                    if path == "replay":
                        replay_rate = rps
                case = f"{path} c={connections}"
                print(
                    f"{case:<14} {server:<8} {rps:>7.0f} {p50:>7.2f} {p99:>7.1f}"
                    f" {rps / base:>5.2f}x {cpu:>10.2f}{verdict}"
                )
    return replay_rate


#: Which file an fsync made durable, by the name strace -y shows (longest pattern first).
FSYNC_FILES = (
    ("audit WAL", "audit.db-wal"),
    ("audit head checkpoint", ".audit.db.head"),
    ("state WAL", "state.db-wal"),
    ("state witness", ".state.db.witness"),
)


def fsync_flood(work: Path, replay_rate: float) -> None:
    """Fsyncs and audit rows for FLOOD replays at 32 connections (strace, seccomp filter)."""
    if shutil.which("strace") is None:
        print("fsync count: strace not found (apt-get install -y strace); not measured")
        return
    state, log = work / "flood-state", work / "fsync.log"
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    trace = ["strace", "-f", "--seccomp-bpf", "-qq", "-y", "-ttt", "-o", str(log)]
    tracer = serve_gateway(state, port, [*trace, "-e", "trace=fsync,fdatasync"])
    (child,) = Path(f"/proc/{tracer.pid}/task/{tracer.pid}/children").read_text().split()
    try:
        captured = envelope(signer(state))
        httpx.post(url + "/v1/messages", content=captured, headers=_JSON).raise_for_status()
        bodies = write_lines(work / "flood.txt", [captured])
        script = write_lines(work / "flood.lua", [WRK_SCRIPT])
        rows_before = audited(state / "audit.db", "REPLAY_DETECTED")
        batches_before = batch_counters(url)
        seconds = max(3, int(FLOOD / max(replay_rate, 1.0) * 2) + 1)
        started = time.time()
        run = wrk(url, int(child), script, bodies, 32, seconds, stop=FLOOD)
        ended = time.time()
        rows = audited(state / "audit.db", "REPLAY_DETECTED") - rows_before
        batches = {k: v - batches_before.get(k, 0.0) for k, v in batch_counters(url).items()}
    finally:
        os.kill(int(child), signal.SIGTERM)
        tracer.wait(timeout=60)
    call = re.compile(r"^\d+\s+(\d+\.\d+) (?:fsync|fdatasync)\(\d+<([^>]*)>")
    calls = [m for ln in log.read_text().splitlines() if (m := call.match(ln))]
    during = [m[2] for m in calls if started <= float(m[1]) <= ended]
    split = {
        label: sum(Path(f).name.startswith(pattern) for f in during)
        for label, pattern in FSYNC_FILES
    }
    split["other"] = len(during) - sum(split.values())
    print(
        f"replay flood, c=32: {run.requests} answered ({run.non_2xx} refused), {rows} audited as"
        f" REPLAY_DETECTED, {len(during)} fsync/fdatasync calls"
        f" = {len(during) * FLOOD / max(rows, 1):.0f} per {FLOOD:,} replays"
        f" (target: a few hundred); server CPU {run.cpu_ms:.2f} ms per request"
    )
    print("  by file: " + ", ".join(f"{k} {v}" for k, v in split.items() if v))
    if rows < run.non_2xx:
        print(f"  MISSED: {run.non_2xx - rows} refused replays have no audit row")
    print(
        "  /metrics group-commit batches: "
        + (", ".join(f"{k} +{v:.0f}" for k, v in batches.items()) or "not exposed")
    )


_JSON = {"content-type": "application/json"}


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--bare-server":
        # The same uvicorn options as `antireplay serve` (cli.serve).
        uvicorn.run(
            bare_app(),
            host="127.0.0.1",
            port=int(sys.argv[2]),
            log_level="warning",
            timeout_graceful_shutdown=10,
        )
        return
    if shutil.which("wrk") is None:
        print("bench_gateway needs wrk, a C HTTP load generator: apt-get install -y wrk")
        raise SystemExit(2)
    bare_port, gateway_port = free_port(), free_port()
    bare = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.bench_gateway", "--bare-server", str(bare_port)]
    )
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        try:
            wait_healthy(f"http://127.0.0.1:{bare_port}", bare, "")
            gateway = serve_gateway(work / "state", gateway_port)
            try:
                runs = measure(
                    work,
                    Server(f"http://127.0.0.1:{bare_port}", bare.pid),
                    Server(f"http://127.0.0.1:{gateway_port}", gateway.pid),
                    signer(work / "state"),
                )
            finally:
                stop(gateway)
        finally:
            stop(bare)
        replay_rate = report(runs)
        fsync_flood(work, replay_rate)


if __name__ == "__main__":
    main()
