"""The load and the servers of ``bench_gateway``: wrk runs, server processes, /proc counters.

* **Servers** run in their own processes: the gateway as users start it
  (``antireplay serve``, the embedded default or a ``--config``), and a bare Starlette
  app on the same uvicorn with the same options, that parses the JSON body and answers
  200 (``python -m benchmarks.bench_gateway --bare-server PORT``).
* **Load** comes from wrk, a C load generator in its own process (keep-alive, loopback,
  one thread): Python clients become the bottleneck long before the servers do.  A Lua
  ``request()`` hook walks a file of bodies, one per line (signed ahead of the run).
* **Counters** are read from /proc over the server's whole process tree (``--workers``
  children included) and every thread: user + system CPU (``stat``) and voluntary +
  involuntary context switches (``task/*/status``), as deltas over one wrk run, per
  answered request.  A thread that exits during the run takes its switches with it, so
  the switch count is a floor; the pools measured here live as long as the server.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import statistics
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import httpx
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ed25519
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

from antireplay.rcan.auth import sign_envelope
from antireplay.wiring import DEMO_KID
from harness import free_port

JSON = {"content-type": "application/json"}
#: Longest wrk run on one set of signed bodies (the window is 30 s: none goes stale).
SLICE_S = 10.0

WRK_SCRIPT = """
local bodies = {}
local i = 0
local headers = {["Content-Type"] = "application/json"}

function init(args)
  for line in io.lines(args[1]) do bodies[#bodies + 1] = line end
end

function request()
  i = i + 1
  if i > #bodies then i = 1 end
  return wrk.format("POST", "/v1/messages", headers, bodies[i])
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


def tree(pid: int) -> list[int]:
    """``pid`` and every descendant (uvicorn's worker processes), from /proc."""
    found, todo = [], [pid]
    while todo:
        p = todo.pop()
        found.append(p)
        try:
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except OSError:  # exited meanwhile
            continue
    return found


def counters(pid: int) -> tuple[float, int]:
    """(CPU seconds, context switches) so far of ``pid``'s process tree, every thread."""
    cpu, switches = 0.0, 0
    for p in tree(pid):
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
            cpu += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
            for task in Path(f"/proc/{p}/task").iterdir():
                for line in (task / "status").read_text().splitlines():
                    if "ctxt_switches:" in line:
                        switches += int(line.split()[1])
        except OSError:
            continue
    return cpu, switches


@dataclass(frozen=True)
class Run:
    """One wrk run: throughput, latency, non-2xx answers and the server's cost per request."""

    rps: float
    p50_ms: float
    p99_ms: float
    requests: int
    non_2xx: int
    cpu_ms: float
    switches: float


def joined(slices: list[Run]) -> Run:
    """One run from its slices: summed, p50 their median, p99 their highest."""
    if len(slices) == 1:
        return slices[0]
    n = sum(r.requests for r in slices)
    duration = sum(r.requests / r.rps for r in slices if r.rps)
    weight = [r.requests / max(n, 1) for r in slices]
    return Run(
        n / duration if duration else 0.0,
        statistics.median(r.p50_ms for r in slices),
        max(r.p99_ms for r in slices),
        n,
        sum(r.non_2xx for r in slices),
        sum(w * r.cpu_ms for w, r in zip(weight, slices, strict=True)),
        sum(w * r.switches for w, r in zip(weight, slices, strict=True)),
    )


def slices_of(seconds: float) -> list[float]:
    """A run of ``seconds`` as slices of at most :data:`SLICE_S`."""
    count = max(1, -(-round(seconds) // round(SLICE_S)))
    return [seconds / count] * count


def p99(values: list[float]) -> float:
    return statistics.quantiles(values, n=100)[98] if len(values) > 1 else values[0]


@dataclass
class Server:
    """A server under test: where it listens, its process, and the pid whose tree is counted."""

    name: str
    url: str
    proc: subprocess.Popen[bytes] | None  # None: started elsewhere, only counted here
    pid: int = 0

    def __post_init__(self) -> None:
        self.pid = self.pid or (self.proc.pid if self.proc is not None else 0)

    def stop(self) -> None:
        """SIGTERM (to what a wrapper runs, if any), SIGKILL after 30 s."""
        if self.proc is None:
            return
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGTERM)
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            for pid in reversed(tree(self.proc.pid)):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            self.proc.wait(timeout=30)


class Wrk:
    """One wrk process against ``server``, started now; :meth:`result` waits for its summary."""

    def __init__(
        self, server: Server, script: Path, bodies: Path, connections: int, seconds: float
    ) -> None:
        self.server = server
        self.before = counters(server.pid)
        args = ["wrk", "-t1", f"-c{connections}", f"-d{max(1, round(seconds))}s", "-s"]
        args += [str(script), server.url, "--", str(bodies)]
        self.proc = subprocess.Popen(args, stdout=subprocess.PIPE, text=True)
        self.deadline = max(1, round(seconds)) + 60

    def interrupt(self) -> Run:
        """Stop the load now (wrk prints its summary on SIGINT) and read its result."""
        self.proc.send_signal(signal.SIGINT)
        return self.result()

    def result(self) -> Run:
        try:
            out, _ = self.proc.communicate(timeout=self.deadline)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise SystemExit(f"{self.server.name}: wrk did not finish") from None
        cpu, switches = (b - a for a, b in zip(self.before, counters(self.server.pid), strict=True))
        line = next((ln for ln in out.splitlines() if ln.startswith("WRK ")), None)
        if line is None:
            raise SystemExit(f"wrk printed no summary:\n{out}")
        data = json.loads(line[4:])
        if data["socket_errors"]:
            raise SystemExit(f"{self.server.name}: {data['socket_errors']} socket errors (wrk)")
        n = max(data["requests"], 1)
        return Run(
            data["requests"] / (data["duration_us"] / 1e6),
            data["p50_us"] / 1e3,
            data["p99_us"] / 1e3,
            data["requests"],
            data["status_errors"],
            cpu * 1e3 / n,
            switches / n,
        )


def settle(server: Server, timeout: float = 10.0) -> None:
    """Wait until ``server`` idles (under 10 % of a core over 0.2 s): no backlog of a previous
    load's work (audit rows, checkpoints) lands on the next measurement."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        before = counters(server.pid)[0]
        time.sleep(0.2)
        if counters(server.pid)[0] - before < 0.02:
            return


def healthy(server: Server, path: str) -> Server:
    """``server`` once it answers ``path`` (a POST to /v1/messages without one)."""
    assert server.proc is not None
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if server.proc.poll() is not None:
            raise SystemExit(f"{server.name}: exited with {server.proc.returncode}")
        try:
            httpx.request(
                "GET" if path else "POST", server.url + (path or "/v1/messages"), content=b"{}"
            )
            return server
        except httpx.HTTPError:
            time.sleep(0.05)
    raise SystemExit(f"{server.name}: did not start")


def bare_server() -> Server:
    port = free_port()
    args = [sys.executable, "-m", "benchmarks.bench_gateway", "--bare-server", str(port)]
    return healthy(Server("bare", f"http://127.0.0.1:{port}", subprocess.Popen(args)), "")


def gateway(
    name: str, state: Path, options: tuple[str, ...] = (), trace: tuple[str, ...] = (),
    launcher: tuple[str, ...] = ("-m", "antireplay"),
) -> Server:  # fmt: skip
    """``antireplay serve`` as users start it (``state``: its ``--state-dir``), optionally
    under a tracer (``trace``: the argv before it; the counted pid is then its child) or
    another ``launcher`` (``python -m benchmarks._gateway_stages OUT``: CPU per stage)."""
    port = free_port()
    args = [sys.executable, *launcher, "serve", "--state-dir", str(state)]
    proc = subprocess.Popen([*trace, *args, *options, "--port", str(port)])
    server = Server(name, f"http://127.0.0.1:{port}", proc)
    if trace:
        deadline = time.monotonic() + 10
        while not (kids := Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()):
            if time.monotonic() > deadline:
                raise SystemExit(f"{name}: the tracer started nothing")
            time.sleep(0.01)
        server.pid = int(kids[0])
    healthy(server, "/healthz")
    wait_ready(server.url)  # past a new state's first-start fence
    return server


def signer(state: Path) -> ed25519.Ed25519PrivateKey:
    key = serialization.load_pem_private_key((state / f"{DEMO_KID}.key.pem").read_bytes(), None)
    assert isinstance(key, ed25519.Ed25519PrivateKey)
    return key


def envelope(key: ed25519.Ed25519PrivateKey, age_s: float = 0.0, cmd: str = "move_forward") -> str:
    """One signed RCAN command for the embedded default's demo operator key, on one line,
    stamped ``age_s`` seconds ago."""
    body = {
        "rcan": "3.2", "rcan_version": "3.2", "msg_id": str(uuid.uuid4()),
        "timestamp": round(time.time() - age_s, 6), "cmd": cmd,
        "target": "rcan://registry.rcan.dev/acme/arm/v2/unit-001",
        "params": {"distance_m": 0.5} if cmd == "move_forward" else {},
    }  # fmt: skip
    return json.dumps(sign_envelope(body, DEMO_KID, "ed25519", key))


def write_lines(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def hog() -> subprocess.Popen[bytes]:
    """A process spinning on one core: other work on the box, as a companion computer has."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


# The flat forms other benchmarks (bench_audit_flood) import from bench_gateway.


def wait_healthy(url: str, proc: subprocess.Popen[bytes], path: str) -> None:
    healthy(Server(url, url, proc), path)


def wait_ready(url: str, timeout_s: float = 60.0) -> None:
    """Until ``/readyz`` answers 200: a new state fences its first start for about
    ``skew_s`` ("fenced until T"), refusing every command stamped before T."""
    deadline = time.monotonic() + timeout_s
    while httpx.get(url + "/readyz").status_code != 200:
        if time.monotonic() > deadline:
            raise SystemExit(f"{url}: not ready within {timeout_s:g} s")
        time.sleep(0.05)


def stop(proc: subprocess.Popen[bytes]) -> None:
    Server("server", "", proc).stop()


def wrk(  # noqa: PLR0917 - the load and its target
    url: str, pid: int, script: Path, bodies: Path, connections: int, seconds: float
) -> Run:
    """One wrk run against ``url``, counting the process tree of ``pid``."""
    return Wrk(Server(url, url, None, pid), script, bodies, connections, seconds).result()
