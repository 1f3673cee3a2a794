"""``antireplay dds …`` as a user runs it: one configuration file, read whole, on real processes.

Each test runs ``sys.executable -m antireplay dds ...`` on its own loopback-only domain id;
the flood comes from this process, a participant without the fleet key (forged samples)
and one replaying stale captures sealed with it (authentic refusals), so both classes of
the refusal auditor write rows.  ``dds write`` stopped while it waits for readers says
what it sent, and a fleet key open to others is warned about.
"""

from __future__ import annotations

import os
import random
import re
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
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
from harness import Reaper, free_port, until
from harness.flood import trail_bytes
from harness.stores import aged_state

SEGMENT = 64 * 1024
BUDGET = 4 * SEGMENT
#: Rotations the flood must cause: twice the budget written.
ROTATIONS = 2 * BUDGET // SEGMENT
#: A long topic name makes every refusal row long (its warning names the topic).
TOPIC = "flood/" + "x" * 200


def _domain() -> int:
    """A domain id no other test module draws from (tests/dds uses 1..~130)."""
    return random.randrange(150, 232)


#: Each test's bound: a hung child fails it (stacks dumped) instead of hanging the run.
pytestmark = pytest.mark.timeout(120)
#: Every ``dds`` process a test here starts (killed when the test ends, passed or failed).
_CHILDREN = Reaper()


@pytest.fixture(autouse=True)
def _reaped() -> Iterator[None]:
    yield
    _CHILDREN.reap()


def _dds(*args: str, **kwargs: object) -> subprocess.Popen[str]:
    return _CHILDREN(
        subprocess.Popen(  # type: ignore[call-overload]
            [sys.executable, "-m", "antireplay", "dds", *args], text=True, **kwargs
        )
    )


def _fleet_key(directory: Path, psk: bytes) -> Path:
    """The fleet key file, mode 0600 (a wider one is warned about on stderr)."""
    path = directory / "fleet.psk"
    path.write_text(psk.hex())
    path.chmod(0o600)
    return path


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
    _fleet_key(tmp_path, psk)
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
    _fleet_key(tmp_path, os.urandom(32))
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
    _fleet_key(tmp_path, os.urandom(32))
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


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=lambda s: s.name)
def test_dds_write_stopped_while_waiting_for_readers_says_what_it_sent_and_exits_0(
    tmp_path: Path, stop: signal.Signals
) -> None:
    """Ctrl-C or SIGTERM on ``dds write`` (nobody reading its topic): one summary line,
    exit 0, as ``dds read`` does; and its fleet key, open to others, is warned about."""
    psk = tmp_path / "fleet.psk"
    psk.write_text(os.urandom(32).hex())
    psk.chmod(0o644)
    topic = f"test/{uuid.uuid4().hex}"  # no reader anywhere on the host
    (tmp_path / "dds.yaml").write_text(
        f"dds:\n  domain_id: {_domain()}\n  loopback_only: true\n  psk_file: {psk}\n"
        f"  writer: {{topic: {topic}, state_file: {tmp_path / 'writer.state'}}}\n"
    )
    write = _dds("write", "--config", "dds.yaml", "ARM", cwd=tmp_path,
                 stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    lines: list[str] = []
    try:
        assert write.stderr is not None
        for line in write.stderr:  # its own 20 s bound ends this if the line never comes
            lines.append(line)
            if "waiting for 1 reader" in line:
                break
        write.send_signal(stop)
        out, err = write.communicate(timeout=30)
    finally:
        write.kill()
    said = "".join(lines) + err
    assert write.returncode == 0, said
    assert said.splitlines()[-1] == f"stopped by {stop.name}: sent 0 of 1 messages", said
    assert said.splitlines()[0] == (
        f"antireplay: warning: dds.psk_file {psk} is open to group or others (mode 0644); "
        f"keep a secret mode 0600: chmod 600 {psk}"
    )
    assert out == "" and "aborted" not in said


def _config(tmp_path: Path, domain: int, store: str, extra: str = "") -> Path:
    config = tmp_path / "dds.yaml"
    config.write_text(
        f"dds:\n  domain_id: {domain}\n  psk_file: {tmp_path / 'fleet.psk'}\n  max_forward_s: 30\n"
        f"  reader: {{topic: robot/cmd, store: '{store}'}}\n  writer: {{topic: robot/cmd}}\n"
        + extra
    )
    return config


def _first_line(process: subprocess.Popen[str]) -> str:
    assert process.stderr is not None
    return process.stderr.readline()


def test_fresh_readers_say_they_are_fenced_and_writers_answer_before_they_send(
    tmp_path: Path,
) -> None:
    """Review finding 6: a reader on a new, empty SQLite file says at start it is fenced
    (until when, why, what lifts it); a one-shot ``dds write`` answers its challenge before
    its first sample, so both commands pass a 30 s fence at once, print as text, and "sent"
    is said for acknowledged samples only; ``--stdin`` does the same line by line."""
    _fleet_key(tmp_path, os.urandom(32))
    config = _config(tmp_path, _domain(), f"sqlite:{tmp_path / 'new.db'}")
    reader = _dds("read", "--config", str(config), "--count", "4", "--timeout", "60",
                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    try:
        line = _first_line(reader)
        while line.startswith("replay state "):  # the store's own word on its lost history
            line = _first_line(reader)
        assert "FENCED until" in line and "has no history" in line and "challenge" in line, line
        start = time.monotonic()
        write = _dds("write", "--config", str(config), "--instance", "arm", "move 1", "move 2",
                     stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
        out, err = write.communicate(timeout=60)
        assert write.returncode == 0, err
        assert out.splitlines()[0].startswith("sent 'move 1' prefix="), out
        assert "answered 1 reader challenge(s)" in err, err
        pipes = {"stdin": subprocess.PIPE, "stdout": subprocess.PIPE, "stderr": subprocess.PIPE}
        stream = _dds("write", "--config", str(config), "--stdin", "--instance", "arm", **pipes)
        out, err = stream.communicate("stop\nhold é\n", timeout=60)
        assert stream.returncode == 0 and out.count("sent ") == 2, (out, err)
        verdicts, _ = reader.communicate(timeout=60)
        elapsed = time.monotonic() - start
    finally:
        reader.kill()
    lines = verdicts.splitlines()
    assert [line.split(" instance=")[0] for line in lines] == ["ACCEPTED"] * 4, verdicts
    assert lines[0].endswith(" 'move 1'") and lines[3].endswith(" 'hold é'"), verdicts
    assert elapsed < 30, f"{elapsed:.1f} s: the fence was waited out, not lifted"


def test_fence_refusals_fold_into_one_line_a_second_and_say_what_is_known(
    tmp_path: Path,
) -> None:
    """Review findings 3 and 6: samples sealed after a memory-store reader started, by a
    writer that never answers, are refused as fenced awaiting an answer (not "sealed before
    this verifier's state began"), in one summary line a second, not one per sample."""
    psk, domain = os.urandom(32), _domain()
    _fleet_key(tmp_path, psk)
    config = _config(tmp_path, domain, "memory")
    reader = _dds("read", "--config", str(config), "--timeout", "4",
                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    try:
        assert "FENCED until" in _first_line(reader)
        silent = SealedWriter(join_domain(domain), "robot/cmd", psk, max_forward_s=30)
        until("DDS discovery", lambda: silent.matched_readers() >= 1)
        for n in range(200):  # sealed now, published without answering any challenge
            silent.publish(silent.seal(f"#{n}".encode(), instance="arm"))
        silent.flush()
        out, err = reader.communicate(timeout=60)
    finally:
        reader.kill()
    lines = out.splitlines()
    assert 1 <= len(lines) <= 5, out
    assert all(line.startswith("REFUSED MESSAGE_STALE restart_fence: ") for line in lines), out
    assert sum(int(line.split(": ")[1].split()[0]) for line in lines) == 200, out
    assert "awaiting a writer's answer to this reader's challenge" in lines[0], out
    assert "stale=200" in err and "before this verifier's state began" not in out + err


def test_fleet_key_rotation_from_the_configuration(tmp_path: Path) -> None:
    """``dds.key_next_file`` + ``dds.key_cutover`` (issue 37): after the cut-over a reader
    refuses a writer still on the old key (``key_retired``) and accepts one configured with
    the rotation (it seals with the new key)."""
    old, domain = os.urandom(32), _domain()
    _fleet_key(tmp_path, old)
    (tmp_path / "next.psk").write_text(os.urandom(32).hex())
    (tmp_path / "next.psk").chmod(0o600)
    past = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(time.time() - 60))
    rotation = f"  key_next_file: {tmp_path / 'next.psk'}\n  key_cutover: {past}\n"
    store = f"sqlite:{aged_state(tmp_path / 'reader.db')}"
    rotated = _config(tmp_path, domain, store, rotation)
    plain = tmp_path / "plain.yaml"
    plain.write_text(rotated.read_text().replace(rotation, ""))
    reader = _dds("read", "--config", str(rotated), "--count", "2", "--timeout", "60",
                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    try:
        assert "no start fence" in _first_line(reader)
        for config, message in ((plain, "old key"), (rotated, "new key")):
            write = _dds("write", "--config", str(config), message,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
            assert write.wait(60) == 0, write.communicate()
        out, _ = reader.communicate(timeout=60)
    finally:
        reader.kill()
    first, second = out.splitlines()
    assert first.startswith("REFUSED SIGNATURE_INVALID key_retired"), out
    assert "retired fleet key" in first and second.startswith("ACCEPTED"), out
    assert second.endswith(" 'new key'"), out
