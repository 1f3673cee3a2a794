"""A real gateway with a small ``audit:`` budget under a stream of accepted commands: the
trail rotates and retention keeps it under budget while it serves, the status page and
``audit tail`` show the newest rows across segments, and after it stops ``audit verify``
proves the chain from where retention cut it."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
from click.testing import CliRunner

from antireplay.audit import verify
from antireplay.audit.segments import bytes_of, rotated
from antireplay.cli import main
from antireplay.cli.demo import command, load_operator_key, write_demo_config
from harness import serving
from harness.stores import aged_state

SEGMENT = 65_536
BUDGET = 4 * SEGMENT


def test_a_serving_gateway_rotates_and_retains_its_trail_within_budget(tmp_path: Path) -> None:
    audit = tmp_path / "audit.db"
    config = write_demo_config(
        tmp_path, audit={"path": str(audit), "segment_bytes": SEGMENT, "max_bytes": BUDGET}
    )
    key = load_operator_key(tmp_path)
    aged_state(tmp_path / "state.db")  # a deployment started earlier: its rows alone
    with serving(config) as gateway, httpx.Client(base_url=gateway.url, timeout=10) as client:

        def send(i: int) -> str:
            raw = command(key, msg_id=f"cmd-{i}")
            reply = client.post("/v1/messages", content=raw,
                                headers={"content-type": "application/json"})  # fmt: skip
            assert reply.status_code == 200, reply.text
            return f"cmd-{i}"

        with ThreadPoolExecutor(8) as pool:
            sent = list(pool.map(send, range(3000)))
        on_disk = sum(bytes_of(file) for _, file in rotated(audit)) + bytes_of(audit)
        assert rotated(audit)[0][0] > 1 and on_disk <= BUDGET  # rotated, and old ones removed
        page = client.get("/status.json").json()["audit"]
        assert page["error"] is None and len(page["records"]) == 20
        # More rows than one 64 KiB segment holds: the tail reads across segments.
        tail = CliRunner().invoke(main, ["audit", "tail", str(audit), "-n", "200", "--json"])
        assert tail.exit_code == 0 and tail.output.count("\n") == 200
    report = verify(audit)
    assert report.ok and report.last_row == 3000 and report.first_segment > 1
    said = CliRunner().invoke(main, ["audit", "verify", str(audit)])
    assert said.exit_code == 0 and "removed by retention; chain verified from row" in said.output
    assert set(sent) == {f"cmd-{i}" for i in range(3000)}
