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

import pytest

from antireplay.audit import verify
from antireplay.audit.segments import rotated
from antireplay.dds.domain import join_domain
from antireplay.dds.topics import SealedWriter
from antireplay.dds.wire import SealedSample
from antireplay.epochs import Kind, derive_key
from antireplay.epochs.policy import seal, to_ns
from antireplay.epochs.sealing import RAW, frame, topic_key
from tests.harness import until

SEGMENT = 64 * 1024
BUDGET = 4 * SEGMENT
#: Rotations the flood must cause: twice the budget written.
ROTATIONS = 2 * BUDGET // SEGMENT
#: A long topic name makes every refusal row long (its warning names the topic).
TOPIC = "flood/" + "x" * 200
#: The trail's files on disk: live and rotated segments, the WAL, a rotation's next segment.
_TRAIL = re.compile(r"dds-audit\.db(\.[0-9]{6,}|-wal|\.next)?")


def _domain() -> int:
    """A domain id no other test module draws from (tests/dds uses 1..~130)."""
    return random.randrange(150, 232)


def _dds(*args: str, **kwargs: object) -> subprocess.Popen[str]:
    return subprocess.Popen(  # type: ignore[call-overload, no-any-return]
        [sys.executable, "-m", "antireplay", "dds", *args], text=True, **kwargs
    )


def _on_disk(trail: Path) -> int:
    """The trail's bytes on disk now, each file once (a rotation hard-links the live one)."""
    files = {}
    for found in trail.parent.glob(trail.name + "*"):
        if _TRAIL.fullmatch(found.name):
            try:
                st = found.stat()
            except FileNotFoundError:  # removed by retention since the listing
                continue
            files[st.st_ino] = st.st_size
    return sum(files.values())


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
        peak, deadline = 0, time.monotonic() + 120
        while _newest_segment(trail) < ROTATIONS:  # several budgets written
            assert time.monotonic() < deadline, f"{_newest_segment(trail)} rotations in 120 s"
            for n in range(100):  # each from its own claimed sender: spread over the keys
                rogue.write(b"forged", instance="")
                sealed = seal(stale_key, Kind.ANNOUNCEMENT, os.urandom(8), long_ago + n,
                              frame("", b"stale capture"))  # fmt: skip
                rogue.publish(SealedSample(instance="", sealed=sealed))
            rogue.flush()
            peak = max(peak, _on_disk(trail))
            assert peak <= BUDGET, f"the trail passed its budget: {peak} bytes on disk"
    finally:
        reader.terminate()
        reader.wait(30)
    errors = (tmp_path / "err").read_text()
    assert reader.returncode == 0, errors
    assert "forged=" in errors and "stale=" in errors, errors
    assert _on_disk(trail) <= BUDGET
    report = verify(trail)  # the chain holds from where retention cut it
    assert report.ok and report.first_row > 1 and report.first_segment > 1, report


@pytest.mark.parametrize(
    ("misplaced", "key", "belongs"),
    [
        ("reader: {store: 'sqlite:r.db'}\n", "reader", "dds:"),
        ("max_age_s: 5\n", "max_age_s", "dds:"),
        ("audit: {path: a.db, max_forward_s: 2}\n", "audit.max_forward_s", "dds:"),
    ],
)
def test_a_dds_key_outside_its_block_exits_2_naming_where_it_belongs(
    tmp_path: Path, misplaced: str, key: str, belongs: str
) -> None:
    """A DDS key at the top level (or in another section) no longer leaves the default in
    force: the command exits 2 naming the key and the block it belongs to."""
    (tmp_path / "fleet.psk").write_text(os.urandom(32).hex())
    config = tmp_path / "antireplay.yaml"
    config.write_text(
        f"dds:\n  domain_id: {_domain()}\n  psk_file: {tmp_path / 'fleet.psk'}\n{misplaced}"
    )
    run = _dds(
        "read", "--config", str(config), "--timeout", "1",
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    out, err = run.communicate(timeout=60)
    assert (run.returncode, out) == (2, ""), err
    assert err.startswith(f"antireplay: error: {key}") and belongs in err, err
    assert len(err.splitlines()) == 1
