"""Signed commands per second through the gateway on loopback, vs the same app unguarded.

Run: ``python -m benchmarks.bench_gateway``.  The servers run as subprocesses; this
process is the load generator (one keep-alive connection, sequential requests), so the
figures are per-connection latency and throughput.  Baseline: a Starlette app on the same
uvicorn that parses the JSON body and answers 200, without the guard.  The gateway's
state and audit live on disk (SQLite, fsync per commit) and, separately, on tmpfs to
show the cost of durability.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import uvicorn
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

from antireplay.demo import JSON, GatewayProcess, command, free_port, load_operator_key
from antireplay.demo import write_demo_config as write_config

N = 600


def bare_app() -> Starlette:
    async def messages(request: Request) -> Response:
        body = json.loads(await request.body())
        return JSONResponse({"accepted": True, "msg_id": body.get("msg_id")})

    return Starlette(routes=[Route("/v1/messages", messages, methods=["POST"])])


def drive(url: str, bodies: list[bytes], expect: int = 200) -> tuple[float, float, float]:
    """(requests/s, p50 ms, p99 ms) for sequential requests on one connection."""
    latencies = []
    with httpx.Client(base_url=url, timeout=30) as client:
        client.post("/v1/messages", content=bodies[0], headers=JSON)  # warm-up
        started = time.perf_counter()
        for body in bodies[1:]:
            t0 = time.perf_counter()
            status = client.post("/v1/messages", content=body, headers=JSON).status_code
            latencies.append(time.perf_counter() - t0)
            if status != expect:
                raise SystemExit(f"{url}: expected HTTP {expect}, got {status}")
        elapsed = time.perf_counter() - started
    cuts = statistics.quantiles(latencies, n=100)
    return len(latencies) / elapsed, cuts[49] * 1e3, cuts[98] * 1e3


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--bare-server":
        uvicorn.run(bare_app(), host="127.0.0.1", port=int(sys.argv[2]), log_level="warning")
        return
    rows = []
    port = free_port()
    bare = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.bench_gateway", "--bare-server", str(port)]
    )
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                httpx.post(f"http://127.0.0.1:{port}/v1/messages", content=b"{}", headers=JSON)
                break
            except httpx.HTTPError:
                time.sleep(0.05)
        with tempfile.TemporaryDirectory() as tmp:
            key_dir = Path(tmp)
            write_config(key_dir)
            key = load_operator_key(key_dir)
            bodies = [command(key) for _ in range(N)]
            rows.append(("bare Starlette (baseline)", drive(f"http://127.0.0.1:{port}", bodies)))
            for label, root in (("disk", Path(tmp)), ("tmpfs", Path("/dev/shm"))):
                with tempfile.TemporaryDirectory(dir=root) as state_dir:
                    state = Path(state_dir)
                    gateway = GatewayProcess(write_config(state, upstream=None))
                    operator = load_operator_key(state)
                    gateway.start()
                    try:
                        fresh = [command(operator) for _ in range(N)]
                        rows.append((f"gateway accept ({label})", drive(gateway.url, fresh)))
                        replay = [fresh[1]] * N
                        rows.append(
                            (f"gateway reject replay ({label})", drive(gateway.url, replay, 409))
                        )
                    finally:
                        gateway.stop()
    finally:
        bare.terminate()
        bare.wait()
    base = rows[0][1][0]
    print(f"{'':<34} {'req/s':>8} {'p50 ms':>8} {'p99 ms':>8} {'overhead':>9}")
    for name, (rps, p50, p99) in rows:
        print(f"{name:<34} {rps:>8.0f} {p50:>8.2f} {p99:>8.2f} {base / rps:>8.2f}x")


if __name__ == "__main__":
    main()
