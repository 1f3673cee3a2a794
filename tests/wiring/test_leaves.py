"""The leaves: the audit block reaches the writer."""

from __future__ import annotations

from pathlib import Path

from antireplay.audit import Retention
from antireplay.config import AuditConfig
from antireplay.wiring import (
    open_audit,
)


def test_the_audit_block_reaches_the_writer(tmp_path: Path) -> None:
    config = AuditConfig(path=str(tmp_path / "audit.db"), segment_bytes=1 << 20,
                         segment_age_s=600, max_bytes=4 << 20, max_age_s=3600)  # fmt: skip
    log = open_audit(config)
    try:
        assert log.path == tmp_path / "audit.db"
        assert log.retention == Retention(1 << 20, 600, 4 << 20, 3600)
    finally:
        log.close()
