"""wrk (Debian ``wrk``) as a test's load: POST a file of bodies in turn and count every
answer's HTTP status, so a test can prove that nothing was dropped while it ran."""

from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

#: Bodies one a line (``args[1]``); each thread counts statuses; ``done`` sums them.
SCRIPT = """
local bodies, i, threads = {}, 0, {}
local headers = {["Content-Type"] = "application/json"}

function setup(thread) table.insert(threads, thread) end

function init(args)
  for line in io.lines(args[1]) do bodies[#bodies + 1] = line end
  statuses = {}
end

function request()
  i = i + 1
  if i > #bodies then i = 1 end
  return wrk.format("POST", "/v1/messages", headers, bodies[i])
end

function response(status, headers, body)
  statuses[status] = (statuses[status] or 0) + 1
end

function done(summary, latency, requests)
  local total = {}
  for _, thread in ipairs(threads) do
    for status, n in pairs(thread:get("statuses")) do
      total[tostring(status)] = (total[tostring(status)] or 0) + n
    end
  end
  local parts = {}
  for status, n in pairs(total) do parts[#parts + 1] = string.format('"%s": %d', status, n) end
  local e = summary.errors
  io.write(string.format('WRK {"requests": %d, "socket_errors": %d, "statuses": {%s}}\\n',
    summary.requests, e.connect + e.read + e.write + e.timeout, table.concat(parts, ", ")))
end
"""


@dataclass(frozen=True)
class WrkRun:
    """What one wrk run answered: requests, socket errors, answers per HTTP status."""

    requests: int
    socket_errors: int
    statuses: dict[int, int]


class WrkLoad:
    """One wrk process POSTing ``bodies`` in turn to ``url``'s ``/v1/messages``, started now."""

    def __init__(
        self, url: str, bodies: list[bytes], directory: Path, *, seconds: int, connections: int = 4
    ) -> None:
        binary = shutil.which("wrk")
        if binary is None:
            pytest.fail("wrk is not installed (Debian package wrk): the load tests need it")
        script, lines = directory / "statuses.lua", directory / "bodies.txt"
        script.write_text(SCRIPT)
        lines.write_bytes(b"\n".join(bodies) + b"\n")
        args = [binary, "-t1", f"-c{connections}", f"-d{seconds}s", "--timeout", "10s", "-s"]
        self.proc = subprocess.Popen(
            [*args, str(script), url, "--", str(lines)], stdout=subprocess.PIPE, text=True
        )
        self.deadline = seconds + 60

    def result(self) -> WrkRun:
        """Wait for wrk's summary."""
        out, _ = self.proc.communicate(timeout=self.deadline)
        line = next((ln for ln in out.splitlines() if ln.startswith("WRK ")), None)
        assert line is not None, f"wrk printed no summary:\n{out}"
        data = json.loads(line[4:])
        statuses = {int(k): v for k, v in data["statuses"].items()}
        return WrkRun(data["requests"], data["socket_errors"], statuses)
