"""``antireplay dds …``: the trail its commands open, the warning for a shared fleet key, and
``dds write`` stopped while it waits for readers."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from antireplay.cli.dds import _audit
from antireplay.config import AuditConfig
from antireplay.dds.config import DdsConfig


def test_dds_commands_open_their_trail_rotated_and_retained(tmp_path: Path) -> None:
    """``dds.audit`` gets the ``audit:`` defaults' segments and budget, and a spill."""
    trail = tmp_path / "dds-audit.db"
    cfg = DdsConfig.from_mapping({"psk_file": str(tmp_path / "psk"), "audit": str(trail)})
    audit = _audit(cfg)
    try:
        defaults = AuditConfig(path=str(trail))
        assert (audit.retention.segment_bytes, audit.retention.max_bytes) == (
            defaults.segment_bytes, defaults.max_bytes,
        )  # fmt: skip
        assert trail.with_name("dds-audit.db.spill").exists()
    finally:
        audit.close()
    assert _audit(DdsConfig.from_mapping({"psk_file": str(tmp_path / "psk")})) is None


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
        f"dds:\n  domain_id: 42\n  loopback_only: true\n  psk_file: {psk}\n"
        f"  writer: {{topic: {topic}, state_file: {tmp_path / 'writer.state'}}}\n"
    )
    write = subprocess.Popen(
        [sys.executable, "-m", "antireplay", "dds", "write", "--config", "dds.yaml", "ARM"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
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
