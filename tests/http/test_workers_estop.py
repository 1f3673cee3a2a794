"""Copies of one captured ESTOP on a real gateway whose robot takes 0.3 s per ESTOP: with 8
copies in flight all the time, ordinary commands find no door held, each new ESTOP of the
operator holds it once, and the copies are delivered (the ESTOP invariant) holding none."""

from __future__ import annotations

import statistics
import threading
import time
from pathlib import Path

import httpx
import pytest

from antireplay.cli.demo import command, load_operator_key, write_demo_config
from harness import metric, post, serving

SLOW_ROBOT = """\
import time


def robot(envelope):
    if envelope.get("safety_event") == "ESTOP":
        time.sleep(0.3)  # the robot takes 0.3 s to answer an ESTOP
    return {"executed": envelope.get("cmd"), "msg_id": envelope.get("msg_id")}
"""
COPIES = 8


def _timed(client: httpx.Client, raw: bytes) -> tuple[httpx.Response, float]:
    started = time.perf_counter()
    reply = post(client, raw)
    return reply, time.perf_counter() - started


def test_copies_of_a_captured_estop_hold_no_door(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "slow_robot.py").write_text(SLOW_ROBOT)
    monkeypatch.chdir(tmp_path)  # the module:function upstream is imported from here
    config = write_demo_config(tmp_path, upstream="slow_robot:robot")
    key = load_operator_key(tmp_path)
    captured = command(key, type=6, safety_event="ESTOP", cmd="estop")
    copies: list[httpx.Response] = []
    stop, arrived = threading.Event(), threading.Condition()
    with serving(config) as gateway, httpx.Client(base_url=gateway.url, timeout=10) as client:
        quiet = [_timed(client, command(key))[1] for _ in range(20)]  # the baseline, same run
        assert post(client, captured).status_code == 200  # delivered; the attacker has a copy

        def attacker() -> None:
            with httpx.Client(base_url=gateway.url, timeout=10) as own:
                while not stop.is_set():
                    reply = post(own, captured)
                    with arrived:
                        copies.append(reply)
                        arrived.notify_all()

        threads = [threading.Thread(target=attacker) for _ in range(COPIES)]
        for thread in threads:
            thread.start()
        try:
            with arrived:  # the attackers have had copies answered: they are in flight
                assert arrived.wait_for(lambda: len(copies) >= 2 * COPIES, timeout=30)
            waits = metric(client, "antireplay_door_waits_total")
            ordinary = [_timed(client, command(key)) for _ in range(20)]
            ordinary_waits = metric(client, "antireplay_door_waits_total") - waits
            new = [_timed(client, command(key, type=6, safety_event="ESTOP", cmd="estop"))
                   for _ in range(3)]  # fmt: skip
            holds = metric(client, "antireplay_door_holds_total")
        finally:
            stop.set()
            for thread in threads:
                thread.join(timeout=30)
        counted = metric(client, "antireplay_estop_copies_total")
    busy = statistics.median(t for _, t in ordinary)
    print(f"ordinary command median {busy * 1000:.1f} ms with {COPIES} copies in flight, "
          f"{statistics.median(quiet) * 1000:.1f} ms without; new ESTOP median "
          f"{statistics.median(t for _, t in new) * 1000:.0f} ms (robot: 300)")  # fmt: skip
    assert all(reply.status_code == 200 for reply, _ in ordinary)
    assert ordinary_waits == 0  # no ordinary command found the door held
    assert all(r.status_code == 200 and r.json().get("warning") is None for r, _ in new)
    assert holds == 1 + 3  # the captured ESTOP once, each new one once; no copy ever held it
    assert copies and counted == len(copies)
    assert all(c.status_code == 200 and c.json()["warning"] == "REPLAY_DETECTED" for c in copies)
