"""The durable path end to end: the gateway users run, under wrk, beside bare Starlette.

Run: ``python -m benchmarks gateway`` (needs ``wrk`` and ``strace``; the router row
MAVProxy, the Redis row ``redis-server``).  Options: ``--rows fresh,flood,c1,estop,inproc,
router,dds,redis,workers,growth,stages``
(default all; ``workers`` only where ``serve --workers`` exists), ``--rounds=3``,
``--seconds=3`` (per wrk run), ``--passes=quiet,loaded`` (default both), ``--quick``
(1-second runs, quiet pass only: under 3 minutes).

Every row of the durable-path table, each against its baseline measured in the same
run (see :mod:`benchmarks._gateway_load` for the servers, the load and the counters):

* **fresh** c=32: every request its own signed Ed25519 envelope; req/s against bare
  Starlette, p99, server CPU ms and context switches per request.
* **flood** c=32: one captured command, accepted once, sent again and again (409).
* **c1**: fresh at one connection (p50), and fsyncs per request counted on a second
  gateway run under ``strace -f --seccomp-bpf -e trace=fsync,fdatasync`` (what ``-c``
  counts, with timestamps so that only the requests' window is counted) for fresh c=1,
  fresh c=32 and the flood, split by the file synced.
* **estop**: 40 fresh ESTOPs from a separate client, one at a time, while wrk (another
  process) floods captured commands at c=32, against the same 40 with no flood; judged
  on the p99 timed inside the gateway (entry to answer), the client's printed beside it
  (httpx shares the cores with wrk and the gateway).
* **inproc**: ``ReplayCache.commit`` on the memory store full at 10,000 entries against
  rcan 3.7.0 ``check_and_record`` (:mod:`benchmarks.bench_window`'s contenders), and a
  refusal (a seen msg_id) on each; rcan's per-refusal warning log is muted.
* **router**: a burst of 5,000 signed frames through ``antireplay mavlink-router``
  (verifying; signing on behalf) against MAVProxy forwarding with signing on
  (:mod:`benchmarks.bench_mavlink`'s sender and launchers).
* **dds**: a sealed DDS topic against a plain one (:mod:`benchmarks.bench_dds`'s
  throughput rounds): samples per second and added latency.
* **redis**: the gateway on a Redis store (a redis-server started here), fresh c=32.
* **workers**: ``serve --workers 2``, fresh c=32, when the option exists.
* **growth**: fresh and replay at c=1, 32 and 128 against bare (lines, no goal).
* **stages**: the gateway under :mod:`benchmarks._gateway_stages`: CPU µs per request of
  each stage and each thread, fresh c=32 and the flood (where a request's CPU goes).

Fresh bodies are signed per slice: a run longer than :data:`SLICE_S` is run as slices of
at most that long, each with bodies signed just before it, so none is stale (the window
is 30 s) whatever ``--seconds`` says; the slices' figures are summed (p50: their median,
p99: their highest).  A row whose answers are not the status it measures (fresh: 2xx;
flood: 409) is a FAIL, whatever its ratio.

Rounds alternate bare and the server under test, figures are medians over rounds, and
the load average is printed at the start and the end.  The *loaded* pass repeats the
rows with a process spinning on one core beside them.  The summary ends with each
row's goal and PASS/MISS (loaded: the fresh p99 and ESTOP goals; the rest for the
record).
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import math
import os
import random
import re
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, fields
from pathlib import Path

import httpx
from cryptography.hazmat.primitives.asymmetric import ed25519

from antireplay import WINDOW_BUILD
from antireplay.wiring import DEMO_KID
from benchmarks import bench_mavlink as mav
from benchmarks import bench_window as window
from benchmarks._gateway_load import (  # the flat forms: bench_audit_flood's
    JSON,
    SLICE_S,
    WRK_SCRIPT,
    Run,
    Server,
    Wrk,
    bare_server,
    envelope,
    gateway,
    hog,
    joined,
    p99,
    settle,
    signer,
    slices_of,
    stop,
    wait_healthy,
    write_lines,
    wrk,
)  # fmt: skip  # fmt: skip
from benchmarks._gateway_rows import (
    accepting,
    has_workers,
    memory_refusals,
    rcan_refusals,
    router_bursts,
)  # fmt: skip
from benchmarks._gateway_stages import profile, stage_lines
from benchmarks._timing import interleaved_ns_per_op

__all__ = ["WRK_SCRIPT", "envelope", "main", "signer", "stop", "wait_healthy", "write_lines", "wrk"]

ROWS = (
    "fresh", "flood", "c1", "estop", "inproc", "router", "dds", "redis", "workers", "growth",
    "stages",
)  # fmt: skip
#: Connections of the growth lines.
GROWTH = (1, 32, 128)
ESTOPS = 40
#: Fsync counting: the traced loads and their connections.
TRACED = {"fresh c=1": 1, "fresh c=32": 32, "flood c=32": 32}
#: Which file an fsync made durable, by the name strace -y shows.
FSYNC_FILES = ("audit.db-wal", ".audit.db.head", "state.db-wal", ".state.db.witness")


@dataclass(frozen=True)
class Options:
    rows: tuple[str, ...]
    rounds: int
    seconds: float
    passes: tuple[str, ...]


def parse(argv: list[str]) -> Options:
    parser = argparse.ArgumentParser(prog="python -m benchmarks gateway")
    parser.add_argument("--rows", default=",".join(ROWS))
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--passes", default=None, help="quiet,loaded (default both)")
    parser.add_argument("--quick", action="store_true", help="1 s runs, quiet pass only")
    args, _ = parser.parse_known_args(argv)  # positional names are python -m benchmarks'
    rows = tuple(r for r in args.rows.split(",") if r)
    unknown = set(rows) - set(ROWS)
    if unknown:
        parser.error(f"unknown rows {sorted(unknown)}; choose from {', '.join(ROWS)}")
    passes = tuple((args.passes or ("quiet" if args.quick else "quiet,loaded")).split(","))
    if set(passes) - {"quiet", "loaded"}:
        parser.error("--passes takes quiet and/or loaded")
    seconds = 1.0 if args.quick and "--seconds" not in " ".join(argv) else args.seconds
    return Options(rows, max(1, args.rounds), seconds, passes)


@dataclass(frozen=True)
class Row:
    """One line of the summary: a measure, its baseline, ours, the goal and the verdict."""

    row: str
    measure: str
    baseline: str
    ours: str
    goal: str
    ok: bool | None  # None: reported, no goal in this pass
    #: Why the answers were not the status measured (a FAIL whatever the ratio), if so.
    broken: str | None = None
    #: What the row measures, printed under it in the summary (when the figure needs it).
    note: str | None = None


def median_run(runs: list[Run]) -> Run:
    return Run(*(statistics.median(getattr(r, f.name) for r in runs) for f in fields(Run)))


class Pass:
    """One pass over the selected rows (quiet, or with a CPU hog beside it)."""

    def __init__(self, opts: Options, work: Path, loaded: bool) -> None:
        self.opts, self.work, self.loaded = opts, work, loaded
        self.details: list[str] = []
        #: Rows whose answers were not the status they measure: why.
        self.broken: dict[str, str] = {}
        self.script = write_lines(work / "wrk.lua", [WRK_SCRIPT])
        self.bare = bare_server()
        self.gw = gateway("gateway", work / "state")
        self.key = signer(work / "state")
        captured = envelope(self.key)
        first = httpx.post(self.gw.url + "/v1/messages", content=captured, headers=JSON)
        if first.status_code != 200:
            raise SystemExit(f"the gateway refused the command to be replayed: {first.text}")
        self.replay = write_lines(work / "replay.txt", [captured])
        for server in (self.bare, self.gw):  # warm-up: imports, caches, connections
            Wrk(server, self.script, self.replay, 32, 1).result()

    def close(self) -> None:
        self.gw.stop()
        self.bare.stop()

    def fresh_bodies(
        self, connections: int, seconds: float, key: ed25519.Ed25519PrivateKey | None = None
    ) -> Path:
        """Signed envelopes for one slice of ``seconds``: more than the fastest server
        answers in it (a server faster still would get copies: its row FAILs, never lies)."""
        per_s = 8_000 if connections > 1 else 1_500
        n = int(per_s * seconds) + 500
        lines = [envelope(key or self.key) for _ in range(n)]
        return write_lines(self.work / "fresh.txt", lines)

    def run(
        self, target: Server, connections: int, fresh: bool, bodies: list[Path] | None = None
    ) -> Run:
        """One measured run of ``--seconds``, in slices, each fresh slice newly signed
        (``bodies``: signed already, one per slice)."""
        parts = []
        for i, seconds in enumerate(slices_of(self.opts.seconds)):
            if bodies is not None:
                file = bodies[i]
            elif fresh:
                file = self.fresh_bodies(connections, seconds)
            else:
                file = self.captured(target)
            settle(target)
            parts.append(Wrk(target, self.script, file, connections, seconds).result())
        return joined(parts)

    def versus_bare(
        self, label: str, server: Server, connections: int, fresh: bool
    ) -> tuple[Run, Run]:
        """Median runs of bare and ``server``, rounds interleaved; a detail line each.  The
        answers that are not the status measured are recorded in ``self.broken``."""
        runs: dict[str, list[Run]] = {"bare": [], server.name: []}
        for _ in range(self.opts.rounds):
            for target in (self.bare, server):
                run = self.run(target, connections, fresh)
                wrong = self.wrong_answers(target, run, fresh)
                if wrong is not None:
                    print(f"  FAIL {label} {target.name}: {wrong}")
                    self.broken[label] = wrong
                runs[target.name].append(run)
        base, ours = median_run(runs["bare"]), median_run(runs[server.name])
        for name, run in (("bare", base), (server.name, ours)):
            self.details.append(
                f"{label:<13} {name:<10} {run.rps:>7.0f} {run.p50_ms:>7.2f} {run.p99_ms:>7.1f}"
                f" {run.rps / base.rps:>5.2f}x {run.cpu_ms:>7.3f} {run.switches:>7.1f}"
            )
        return base, ours

    def captured(self, target: Server, key: ed25519.Ed25519PrivateKey | None = None) -> Path:
        """A command accepted just now, to be replayed (``self.replay``): a capture older
        than the window would be refused as stale, not as a replay."""
        if target is not self.bare:
            body = envelope(key or self.key)
            answer = httpx.post(target.url + "/v1/messages", content=body, headers=JSON)
            if answer.status_code != 200:
                raise SystemExit(f"{target.name} refused the command to be replayed: {answer.text}")
            write_lines(self.replay, [body])
        return self.replay

    def wrong_answers(self, target: Server, run: Run, fresh: bool) -> str | None:
        """Why ``run``'s answers are not the status it measures (``None``: they are): bare
        answers 200 to all; the gateway 2xx to fresh commands, 409 to the captured one
        (wrk counts answers >= 400; one probe says that they are 409)."""
        if target is self.bare or fresh:
            return None if run.non_2xx == 0 else f"{run.non_2xx} of {run.requests} not 2xx"
        if run.non_2xx != run.requests:
            return f"{run.requests - run.non_2xx} of {run.requests} not refused"
        probe = httpx.post(target.url + "/v1/messages", content=self.replay.read_bytes().strip(),
                           headers=JSON)  # fmt: skip
        return None if probe.status_code == 409 else f"the replay answered {probe.status_code}"

    def verdict(self, label: str, ok: bool | None) -> tuple[bool | None, str | None]:
        """The row's verdict and why its answers were wrong (then never a PASS)."""
        broken = self.broken.get(label)
        return (False if broken is not None else ok), broken

    # -- the rows --------------------------------------------------------------------

    def fresh(self) -> list[Row]:
        base, ours = self.versus_bare("fresh c=32", self.gw, 32, fresh=True)
        ratio = ours.rps / base.rps
        if self.loaded:
            ok, goal = ours.p99_ms <= 3 * base.p99_ms, "p99 <= 3x bare (loaded)"
        else:
            ok = ratio >= 0.25 and ours.p99_ms <= 15 and ours.cpu_ms <= 0.35
            goal = ">= 0.25x, p99 <= 15 ms, <= 0.35 ms CPU"
        verdict, broken = self.verdict("fresh c=32", ok)
        return [
            Row(
                "fresh c=32",
                "req/s (ratio), p99, CPU/request",
                f"{base.rps:,.0f}, p99 {base.p99_ms:.1f}, {base.cpu_ms:.3f} ms",
                f"{ours.rps:,.0f} ({ratio:.2f}x), p99 {ours.p99_ms:.1f}, {ours.cpu_ms:.3f} ms",
                goal,
                verdict,
                broken,
            )
        ]

    def flood(self) -> list[Row]:
        base, ours = self.versus_bare("flood c=32", self.gw, 32, fresh=False)
        ratio = ours.rps / base.rps
        ok, broken = self.verdict("flood c=32", None if self.loaded else ratio >= 0.95)
        return [
            Row(
                "flood c=32",
                "req/s (ratio), p99, CPU/request",
                f"{base.rps:,.0f}, p99 {base.p99_ms:.1f}, {base.cpu_ms:.3f} ms",
                f"{ours.rps:,.0f} ({ratio:.2f}x), p99 {ours.p99_ms:.1f}, {ours.cpu_ms:.3f} ms",
                ">= 0.95x",
                ok,
                broken,
            )
        ]

    def growth(self) -> list[Row]:
        """Fresh and replay at c=1, 32 and 128 against bare: how each grows (no goal)."""
        rows = []
        for fresh in (True, False):
            for connections in GROWTH:
                label = f"{'fresh' if fresh else 'replay'} c={connections}"
                base, ours = self.versus_bare(label, self.gw, connections, fresh)
                ok, broken = self.verdict(label, None)
                rows.append(Row(
                    "growth", label, f"{base.rps:,.0f}, p99 {base.p99_ms:.1f} ms",
                    f"{ours.rps:,.0f} ({ours.rps / base.rps:.2f}x), p99 {ours.p99_ms:.1f} ms",
                    "(how it grows)", ok, broken,
                ))  # fmt: skip
        return rows

    def stages(self) -> list[Row]:
        """CPU µs per request by stage and by thread, fresh c=32 and the flood, on a
        gateway under :mod:`benchmarks._gateway_stages` (its own state)."""
        out = self.work / "stages.json"
        launcher = ("-m", "benchmarks._gateway_stages", str(out))
        gw = gateway("stages", self.work / "stages-state", launcher=launcher)
        try:
            key = signer(self.work / "stages-state")
            accepting(gw, key)
            captured = envelope(key)
            httpx.post(gw.url + "/v1/messages", content=captured, headers=JSON)
            replay = write_lines(self.work / "stages-replay.txt", [captured])
            for label, fresh in (("fresh c=32", True), ("flood c=32", False)):
                bodies = self.fresh_bodies(32, min(self.opts.seconds, SLICE_S), key)
                settle(gw)
                before = profile(gw, out)
                run = Wrk(gw, self.script, bodies if fresh else replay, 32,
                          min(self.opts.seconds, SLICE_S)).result()  # fmt: skip
                after = profile(gw, out)
                self.details += stage_lines(label, before, after, run)
        finally:
            gw.stop()
        return []

    def c1(self) -> list[Row]:
        base, ours = self.versus_bare("fresh c=1", self.gw, 1, fresh=True)
        per_request = self.fsyncs()
        one = per_request.get("fresh c=1", float("nan"))
        return [
            Row(
                "fresh c=1",
                "p50; fsyncs per request",
                f"p50 {base.p50_ms:.2f} ms",
                f"p50 {ours.p50_ms:.2f} ms; {one:.2f} fsyncs",
                "one fsync per command",
                *self.verdict("fresh c=1", one <= 1.05),
            )
        ]

    def fsyncs(self) -> dict[str, float]:
        """Fsyncs per request of each TRACED load, on a gateway under strace."""
        if shutil.which("strace") is None:
            self.details.append("fsyncs: strace not found (apt-get install -y strace)")
            return {}
        log = self.work / "fsync.log"
        trace = ("strace", "-f", "--seccomp-bpf", "-qq", "-y", "-ttt", "-o", str(log),
                 "-e", "trace=fsync,fdatasync")  # fmt: skip
        traced = gateway("traced", self.work / "traced-state", trace=trace)
        windows: dict[str, tuple[float, float, int]] = {}
        try:
            key = signer(self.work / "traced-state")
            captured = envelope(key)
            httpx.post(traced.url + "/v1/messages", content=captured, headers=JSON)
            replay = write_lines(self.work / "traced-replay.txt", [captured])
            for label, connections in TRACED.items():
                fresh = label.startswith("fresh")
                bodies = self.fresh_bodies(connections, self.opts.seconds, key) if fresh else replay
                settle(traced)
                started = time.time()
                run = Wrk(traced, self.script, bodies, connections, self.opts.seconds).result()
                settle(traced)  # the run's last batch is its own
                windows[label] = started, time.time(), run.requests
        finally:
            traced.stop()
        call = re.compile(r"^\d+\s+(\d+\.\d+) (?:fsync|fdatasync)\(\d+<([^>]*)>")
        calls = [(float(m[1]), Path(m[2]).name) for ln in log.read_text().splitlines()
                 if (m := call.match(ln))]  # fmt: skip
        out = {}
        for label, (start, end, requests) in windows.items():
            during = [name for at, name in calls if start <= at <= end]
            out[label] = len(during) / max(requests, 1)
            split = {p: sum(n.startswith(p) for n in during) for p in FSYNC_FILES}
            split["other"] = len(during) - sum(split.values())
            self.details.append(
                f"fsyncs, {label}: {len(during)} for {requests} requests = {out[label]:.2f}"
                " per request (" + ", ".join(f"{k} {v}" for k, v in split.items() if v) + ")"
            )
        return out

    def estop_latencies(
        self, gw: Server, key: ed25519.Ed25519PrivateKey, flood: bool
    ) -> tuple[list[float], int]:
        """Latency (ms) of ESTOPS fresh ESTOPs, one at a time, with or without a flood."""
        bodies = [envelope(key, cmd="ESTOP") for _ in range(ESTOPS + 1)]
        settle(gw)
        with httpx.Client(headers=JSON) as client:
            client.post(gw.url + "/v1/messages", content=bodies.pop())  # the connection
            replay = self.captured(gw, key) if flood else None
            load = Wrk(gw, self.script, replay, 32, 120) if replay is not None else None
            time.sleep(0.3)  # wrk connected and saturating
            latencies, accepted = [], 0
            for body in bodies:
                started = time.perf_counter()
                answer = client.post(gw.url + "/v1/messages", content=body)
                latencies.append((time.perf_counter() - started) * 1e3)
                accepted += answer.status_code == 200
                time.sleep(0.02)
            if load is not None:
                run = load.interrupt()
                self.details.append(f"ESTOPs sent during a flood of {run.rps:,.0f} req/s")
        return latencies, accepted

    def estop(self) -> list[Row]:
        """On a gateway that also times each ESTOP inside itself (_gateway_stages): the
        client's p99 beside the gateway's, so a client starved of a core shows as such."""
        out = self.work / "estop.json"
        launcher = ("-m", "benchmarks._gateway_stages", str(out))
        gw = gateway("estop", self.work / "estop-state", launcher=launcher)
        key = signer(self.work / "estop-state")
        quiet: list[float] = []
        flooded: list[float] = []
        accepted: list[int] = []
        inside: dict[str, list[float]] = {"quiet": [], "flooded": []}
        try:
            accepting(gw, key)
            for _ in range(self.opts.rounds):
                for label, flood in (("quiet", False), ("flooded", True)):
                    was = len(profile(gw, out)["estop_ms"])
                    latencies, n = self.estop_latencies(gw, key, flood)
                    timed = profile(gw, out)["estop_ms"][was:]
                    inside[label].append(p99(timed) if timed else float("nan"))
                    (flooded if flood else quiet).append(p99(latencies))
                    accepted.append(n if flood else ESTOPS)
        finally:
            gw.stop()
        q99, f99 = statistics.median(quiet), statistics.median(flooded)
        gq, gf = statistics.median(inside["quiet"]), statistics.median(inside["flooded"])
        self.details.append(f"ESTOP p99 per round, client: quiet {quiet}, flooded {flooded} (ms)")
        self.details.append(
            f"ESTOP p99 per round, inside the gateway: quiet {inside['quiet']}, flooded"
            f" {inside['flooded']} (ms); medians {gq:.1f} and {gf:.1f} ms ({gf / gq:.1f}x)"
        )
        missing = [f"{ESTOPS - min(accepted)} ESTOPs not 200"] if min(accepted) < ESTOPS else []
        if math.isnan(gq) or math.isnan(gf):
            missing.append("no in-gateway timing")
        return [
            Row(
                "ESTOP in flood",
                "p99 in the gateway (accepted)",
                f"no flood: p99 {gq:.1f} ms",
                f"p99 {gf:.1f} ms, {gf / gq:.1f}x ({min(accepted)}/{ESTOPS})",
                "p99 <= 2x no flood",
                gf <= 2 * gq,
                "; ".join(missing) or None,
                f"judged inside the gateway, from the request's entry to its answer; the"
                f" client's p99 beside it: {f99:.1f} ms against {q99:.1f} quiet,"
                f" {f99 / q99:.1f}x: it adds httpx, which shares the {os.cpu_count()} cores"
                " with wrk and the gateway, so it waits for a core as well; the flood is"
                " wrk, another process",
            )
        ]

    def inproc(self) -> list[Row]:
        size, batch, rcan_batch = 10_000, 20_000, 5_000
        logging.getLogger("rcan.replay").setLevel(logging.ERROR)  # its warning per refusal
        work = window.Workload(size, batch)
        contenders = [
            (window.memory_full(work, size), batch),
            (window.rcan_full(size, rcan_batch), rcan_batch),
            (memory_refusals(work, size, batch), batch),
            (rcan_refusals(size, batch), batch),
        ]
        ours, rcan, refuse, rcan_refuse = interleaved_ns_per_op(contenders, window.REPEATS)
        loaded = self.loaded
        return [
            Row("in-process", f"commit, memory, 10k ({WINDOW_BUILD})", f"rcan {rcan:,.0f} ns",
                f"{ours:,.0f} ns ({rcan / ours:.2f}x)", ">= 3x rcan",
                None if loaded else rcan / ours >= 3),
            Row("refusals", "seen msg_id, full 10k", f"rcan {rcan_refuse:,.0f} ns",
                f"{refuse:,.0f} ns ({rcan_refuse / refuse:.2f}x)", ">= 1x rcan",
                None if loaded else rcan_refuse / refuse >= 1),
        ]  # fmt: skip

    def router(self) -> list[Row]:
        rates = router_bursts(self.opts.rounds)
        base = rates["mavproxy"]
        self.details.append(
            f"router burst of {mav.BURST}, frames/s: "
            + ", ".join(f"{k} {v:,.0f}" for k, v in rates.items())
        )
        verify, behalf = rates["verifying"] / base, rates["on behalf"] / base
        return [
            Row("router verify", f"burst {mav.BURST:,} frames/s", f"MAVProxy {base:,.0f}",
                f"{rates['verifying']:,.0f} ({verify:.2f}x)", ">= 2.5x MAVProxy",
                None if self.loaded else verify >= 2.5),
            Row("router behalf", f"burst {mav.BURST:,} frames/s", f"MAVProxy {base:,.0f}",
                f"{rates['on behalf']:,.0f} ({behalf:.2f}x)", ">= 1.5x MAVProxy",
                None if self.loaded else behalf >= 1.5),
        ]  # fmt: skip

    def dds(self) -> list[Row]:
        """The sealed DDS topic beside a plain one (:mod:`benchmarks.bench_dds`'s rounds),
        so that every row of the table is in one summary."""
        from benchmarks import bench_dds  # noqa: PLC0415 - needs the dds extra (cyclonedds)

        got = bench_dds.throughput_rows(random.randrange(150, 225), self.opts.rounds)
        ratio, added = got["ratio"], got["added_us"]
        refused = int(got["refused"])
        return [
            Row("sealed DDS", "samples/s, latency", "plain Cyclone DDS topic",
                f"{ratio:.2f}x, +{added:.0f} us (CPU +{got['cpu_added_us']:.1f} us)",
                ">= 0.7x, <= +15 us", None if self.loaded else ratio >= 0.7 and added <= 15,
                broken=f"{refused} samples refused or not whole" if refused else None),
        ]  # fmt: skip

    def redis(self) -> list[Row]:
        from harness.redis_server import RedisServer  # noqa: PLC0415 - needs pytest

        directory = self.work / "redis"
        directory.mkdir(exist_ok=True)
        server = RedisServer(directory)
        server.start()
        public = self.work / "state" / f"{DEMO_KID}.pub.pem"
        config = write_lines(directory / "gateway.yaml", [
            f"store: {server.url}", f"audit: {directory / 'audit.db'}", "keys:",
            f"  - {{kid: {DEMO_KID}, owner: operator, alg: ed25519, public_keys: [{public}],",
            "     scopes: [control, safety]}",
        ])  # fmt: skip
        try:
            gw = gateway("redis", directory, ("--config", str(config)))
            try:
                accepting(gw, self.key)
                base, ours = self.versus_bare("redis c=32", gw, 32, fresh=True)
            finally:
                gw.stop()
        finally:
            server.stop()
        ratio = ours.rps / base.rps
        return [
            Row(
                "Redis store",
                "fresh c=32 req/s",
                f"{base.rps:,.0f}",
                f"{ours.rps:,.0f} ({ratio:.2f}x), p99 {ours.p99_ms:.1f} ms",
                ">= 0.2x",
                *self.verdict("redis c=32", None if self.loaded else ratio >= 0.2),
            )
        ]

    def workers(self) -> list[Row]:
        if not has_workers():
            self.details.append("workers: `antireplay serve` has no --workers; row skipped")
            return []
        gw = gateway("workers=2", self.work / "workers-state", ("--workers", "2"))
        try:
            self.key, key = signer(self.work / "workers-state"), self.key
            try:
                accepting(gw, self.key)
                base, ours = self.versus_bare("workers=2", gw, 32, fresh=True)
            finally:
                self.key = key
        finally:
            gw.stop()
        self.details.append(
            f"scaling model: {ours.cpu_ms:.3f} CPU ms per fresh request ="
            f" {1e3 / ours.cpu_ms:,.0f} req/s per core, before the load generator's share"
        )
        return [
            Row(
                "--workers 2",
                "fresh c=32 req/s",
                f"{base.rps:,.0f}",
                f"{ours.rps:,.0f} ({ours.rps / base.rps:.2f}x), p99 {ours.p99_ms:.1f} ms",
                "(2 cores: see scaling)",
                *self.verdict("workers=2", None),
            )
        ]


def run_pass(opts: Options, loaded: bool) -> list[tuple[str, Row]]:
    name = "loaded" if loaded else "quiet"
    print(f"\n-- {name} pass" + (" (a process spinning on one core beside it)" if loaded else ""))
    spinner = hog() if loaded else None
    try:
        with tempfile.TemporaryDirectory() as tmp:
            bench = Pass(opts, Path(tmp), loaded)
            rows: list[Row] = []
            try:
                for row in opts.rows:
                    began = time.monotonic()
                    rows += getattr(bench, row)()
                    print(f"   {row}: {time.monotonic() - began:.0f} s", flush=True)
            finally:
                bench.close()
    finally:
        if spinner is not None:
            spinner.kill()
            spinner.wait()
    print(f"{'case':<13} {'server':<10} {'req/s':>7} {'p50 ms':>7} {'p99 ms':>7} {'ratio':>6}"
          f" {'CPU ms':>7} {'ctx sw':>7}   (per request, medians)")  # fmt: skip
    for line in bench.details:
        print(line)
    return [(name, r) for r in rows]


def summary(rows: list[tuple[str, Row]]) -> None:
    print("\nsummary (goals: the durable-path table; loaded: fresh p99 and ESTOP goals only)")
    print(f"{'row':<15} {'pass':<7} {'measure':<30} {'baseline (same run)':<28}"
          f" {'antireplay':<34} {'goal':<24} verdict")  # fmt: skip
    for name, r in rows:
        verdict = "-" if r.ok is None else "PASS" if r.ok else "MISS"
        ours = r.ours
        if r.broken is not None:  # answers not the status measured: no ratio stands
            verdict, ours = "FAIL", f"answers wrong: {r.broken}"
        print(f"{r.row:<15} {name:<7} {r.measure:<30} {r.baseline:<28} {ours:<34}"
              f" {r.goal:<24} {verdict}")  # fmt: skip
        if r.note is not None:
            print(f"{'':<15} {'':<7} ({r.note})")


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    if len(args) == 2 and args[0] == "--bare-server":
        import uvicorn  # noqa: PLC0415

        from benchmarks._gateway_load import bare_app  # noqa: PLC0415

        # The same uvicorn options as `antireplay serve` (cli.serve).
        uvicorn.run(bare_app(), host="127.0.0.1", port=int(args[1]), log_level="warning",
                    timeout_graceful_shutdown=10)  # fmt: skip
        return
    opts = parse(args)
    for tool in ("wrk",):
        if shutil.which(tool) is None:
            raise SystemExit(f"bench_gateway needs {tool}: apt-get install -y {tool}")
    started = time.monotonic()
    print(
        f"load average at start: {os.getloadavg()}; rows {','.join(opts.rows)};"
        f" {opts.rounds} rounds of {opts.seconds:g} s; wrk -t1, keep-alive, loopback"
    )
    http = "httptools" if importlib.util.find_spec("httptools") else "h11"
    loop = "uvloop" if importlib.util.find_spec("uvloop") else "asyncio"
    print(f"uvicorn picks http={http}, loop={loop} (both servers); {os.cpu_count()} cores")
    rows: list[tuple[str, Row]] = []
    for name in opts.passes:
        rows += run_pass(opts, loaded=name == "loaded")
    summary(rows)
    print(f"load average at end: {os.getloadavg()}; {time.monotonic() - started:.0f} s")


if __name__ == "__main__":
    main()
