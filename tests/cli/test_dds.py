"""``antireplay dds …`` as a user runs it: one configuration file, read whole, on real processes.

Each test runs ``sys.executable -m antireplay dds ...`` on its own loopback-only domain id;
the flood comes from this process, a participant without the fleet key (forged samples)
and one replaying stale captures sealed with it (authentic refusals), so both classes of
the refusal auditor write rows.
"""

from __future__ import annotations

import os
import random
import re
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from antireplay.audit import verify
from antireplay.audit.segments import rotated
from antireplay.dds.domain import join_domain
from antireplay.dds.topics import SealedWriter
from antireplay.dds.wire import SealedSample
from antireplay.epochs import Kind, derive_key
from antireplay.epochs.policy import seal, to_ns
from antireplay.epochs.sealing import RAW, frame, topic_key
from harness import free_port, until
from harness.flood import trail_bytes

SEGMENT = 64 * 1024
BUDGET = 4 * SEGMENT
#: Rotations the flood must cause: twice the budget written.
ROTATIONS = 2 * BUDGET // SEGMENT
#: A long topic name makes every refusal row long (its warning names the topic).
TOPIC = "flood/" + "x" * 200


def _domain() -> int:
    """A domain id no other test module draws from (tests/dds uses 1..~130)."""
    return random.randrange(150, 232)


def _dds(*args: str, **kwargs: object) -> subprocess.Popen[str]:
    return subprocess.Popen(  # type: ignore[call-overload, no-any-return]
        [sys.executable, "-m", "antireplay", "dds", *args], text=True, **kwargs
    )


def _newest_segment(trail: Path) -> int:
    """The number of the newest rotated segment on disk (0: none yet), from the file names
    only: a reader holding the live segment open would delay its rotation."""
    return max((n for n, _ in rotated(trail)), default=0)


def test_reader_trail_stays_within_audit_max_bytes_under_a_refusal_flood(
    tmp_path: Path,
) -> None:
    """``audit.max_bytes`` and ``audit.segment_bytes`` in the file reach the ``dds read``
    trail: a flood of forged and stale samples writes several budgets' worth of rows, and
    the trail's bytes on disk, sampled throughout, never pass the budget."""
    psk, domain = os.urandom(32), _domain()
    (tmp_path / "fleet.psk").write_text(psk.hex())
    trail = tmp_path / "dds-audit.db"
    config = tmp_path / "antireplay.yaml"
    config.write_text(
        f"audit: {{segment_bytes: {SEGMENT}, max_bytes: {BUDGET}}}\n"
        f"dds:\n  domain_id: {domain}\n  psk_file: {tmp_path / 'fleet.psk'}\n"
        f"  audit: {trail}\n  reader: {{topic: {TOPIC}}}\n"
    )
    with (tmp_path / "out").open("w") as out, (tmp_path / "err").open("w") as err:
        reader = _dds("read", "--config", str(config), stdout=out, stderr=err)
    try:
        rogue = SealedWriter(join_domain(domain), TOPIC, os.urandom(32))
        until("DDS discovery", lambda: rogue.matched_readers() >= 1)
        stale_key = derive_key(topic_key(psk, TOPIC, RAW, domain), Kind.ANNOUNCEMENT)
        long_ago = to_ns(time.time() - 600)
        senders = [os.urandom(8) for _ in range(16)]  # enough to fill the authentic budget
        peak, deadline, sent = 0, time.monotonic() + 120, 0
        while _newest_segment(trail) < ROTATIONS:  # several budgets written
            assert time.monotonic() < deadline, f"{_newest_segment(trail)} rotations in 120 s"
            for _ in range(100):
                rogue.write(b"forged", instance="")
                sealed = seal(stale_key, Kind.ANNOUNCEMENT, senders[sent % 16], long_ago + sent,
                              frame("", b"stale capture"))  # fmt: skip
                rogue.publish(SealedSample(instance="", sealed=sealed))
                sent += 1
            rogue.flush()
            peak = max(peak, trail_bytes(trail))
            assert peak <= BUDGET, f"the trail passed its budget: {peak} bytes on disk"
    finally:
        reader.terminate()
        reader.wait(30)
    errors = (tmp_path / "err").read_text()
    assert reader.returncode == 0, errors
    assert "forged=" in errors and "stale=" in errors, errors
    assert trail_bytes(trail) <= BUDGET
    report = verify(trail)  # the chain holds from where retention cut it
    assert report.ok and report.first_row > 1 and report.first_segment > 1, report


@pytest.mark.parametrize(
    ("command", "text", "said"),
    [
        # a DDS key outside its block: refused naming the key and where it belongs
        ("read", "dds: {psk_file: PSK}\nreader: {store: 'sqlite:r.db'}", "reader: not a top-level"),
        ("read", "dds: {psk_file: PSK}\nmax_age_s: 5", "max_age_s: not a top-level"),
        ("relay", "dds: {psk_file: PSK}\naudit: {max_forward_s: 2}", "audit.max_forward_s"),
        ("read", "dds: {psk_file: PSK, reader: {max_age_s: 5}}", "dds.reader.max_age_s"),
        # and the block's own mistakes
        ("read", "dds: {psk_file: gone.psk}", "dds.psk_file: file not found: gone.psk"),
        ("write", "dds: {psk_file: gone.psk}", "dds.psk_file: file not found: gone.psk"),
        ("relay", "dds: {psk_file: gone.psk}", "dds.psk_file: file not found"),
        ("relay", "dds: {psk_file: PSK}", "dds.relay=None: allowed a relay block"),
        ("replay", "dds: {psk_file: PSK, max_age_s: fast}", "dds.max_age_s"),
        ("read", "audit: {segment_bytes: 65536}", "dds=None: allowed a dds: block"),
    ],
)
def test_config_mistakes_exit_2_with_one_line_naming_the_key(
    tmp_path: Path, command: str, text: str, said: str
) -> None:
    """A key where it does not belong no longer leaves a default in force (a top-level
    ``reader:`` or ``max_age_s:`` ran on the memory store and 30 s before): every mistake
    is one line naming the key, with exit status 2, before anything is opened."""
    (tmp_path / "fleet.psk").write_text(os.urandom(32).hex())
    config = tmp_path / "antireplay.yaml"
    config.write_text(text.replace("PSK", str(tmp_path / "fleet.psk")) + "\n")
    (tmp_path / "cap.jsonl").write_text("")
    extra = {"read": ["--timeout", "1"], "write": ["hello"], "relay": ["--duration", "1"],
             "replay": [str(tmp_path / "cap.jsonl")]}[command]  # fmt: skip
    run = _dds(command, "--config", str(config), *extra,
               stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    out, err = run.communicate(timeout=60)
    assert (run.returncode, out) == (2, ""), err
    assert len(err.splitlines()) == 1 and err.startswith("antireplay: error: "), err
    assert said in err, err
    if "top-level" in said or said == "audit.max_forward_s":
        assert "belongs under" in err and "dds:" in err, err


def test_reader_serves_its_verdicts_and_trail_to_prometheus(tmp_path: Path) -> None:
    """``--metrics-port``: the reader's verdicts per outcome and its trail's bytes, as the
    gateway and the router serve theirs."""
    domain, port = _domain(), free_port()
    (tmp_path / "fleet.psk").write_text(os.urandom(32).hex())
    config = tmp_path / "antireplay.yaml"
    config.write_text(
        f"dds:\n  domain_id: {domain}\n  psk_file: {tmp_path / 'fleet.psk'}\n"
        f"  audit: {tmp_path / 'dds-audit.db'}\n  reader: {{topic: robot/cmd}}\n"
    )
    reader = _dds("read", "--config", str(config), "--metrics-port", str(port),
                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)  # fmt: skip
    try:
        rogue = SealedWriter(join_domain(domain), "robot/cmd", os.urandom(32))
        until("DDS discovery", lambda: rogue.matched_readers() >= 1)
        rogue.write(b"forged", instance="arm")
        rogue.flush()

        def scraped() -> str:
            try:
                return httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=5).text
            except httpx.TransportError:  # not listening yet
                return ""

        until("the forged sample counted", lambda: 'outcome="forged"} 1.0' in scraped())
        text = scraped()
        assert 'antireplay_dds_verdicts_total{endpoint="robot/cmd",outcome="forged"} 1.0' in text
        assert re.search(r"^antireplay_audit_trail_bytes [1-9]", text, re.MULTILINE), text
    finally:
        reader.terminate()
        _, err = reader.communicate(timeout=30)
    assert reader.returncode == 0, err
