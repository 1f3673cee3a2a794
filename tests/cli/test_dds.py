"""``antireplay dds …``: the trail its commands open."""

from __future__ import annotations

from pathlib import Path

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
