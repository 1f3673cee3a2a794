"""The DDS commands' wiring: one AppConfig in, endpoints on leaves opened like ``serve``'s."""

from __future__ import annotations

import os
import random
from pathlib import Path

import pytest

from antireplay.config import AppConfig
from antireplay.core.errors import ConfigError
from antireplay.state.sqlite import SqliteStore
from antireplay.wiring.dds import DdsCommand


def _config(tmp_path: Path, **sections: dict[str, object]) -> AppConfig:
    """A file with a ``dds:`` block on a domain id of its own, plus ``sections``."""
    (tmp_path / "fleet.psk").write_text(os.urandom(32).hex())
    dds = {"domain_id": random.randrange(150, 232), "psk_file": str(tmp_path / "fleet.psk")}
    dds.update(sections.pop("dds", {}))
    return AppConfig.from_mapping({**sections, "dds": dds})


def test_the_trail_gets_the_audit_blocks_retention_spill_and_floors(tmp_path: Path) -> None:
    trail = tmp_path / "dds-audit.db"
    config = _config(
        tmp_path,
        audit={"segment_bytes": 65_536, "max_bytes": 262_144},
        audit_space={"min_free_bytes": 1 << 60, "refuse_free_bytes": 0},  # always low
        dds={"audit": str(trail)},
    )
    with DdsCommand(config) as wired:
        assert wired.audit is not None and wired.quiet is not None
        assert (wired.audit.retention.segment_bytes, wired.audit.retention.max_bytes) == (
            65_536, 262_144,
        )  # fmt: skip
        assert trail.with_name("dds-audit.db.spill").exists()
        assert wired.quiet()  # below the first floor: refusals counted, not written
        reader = wired.reader("robot/cmd")
        assert reader._refusals.quiet()


def test_no_trail_unless_dds_audit_names_one(tmp_path: Path) -> None:
    with DdsCommand(_config(tmp_path)) as wired:
        assert wired.audit is None and wired.quiet is None


def test_a_sqlite_store_is_opened_by_the_leaves_and_closed_after_its_reader(
    tmp_path: Path,
) -> None:
    spec = f"sqlite:{tmp_path / 'reader.db'}"
    wired = DdsCommand(_config(tmp_path, dds={"reader": {"store": spec}}))
    reader = wired.reader()
    assert isinstance(reader.verifier.store, SqliteStore)
    assert reader.verifier.fenced()  # a new SQLite file has no history: fenced like memory
    wired.close()
    reopened = DdsCommand(_config(tmp_path, dds={"reader": {"store": spec}}))  # released
    reopened.reader().close()
    reopened.close()


def test_a_relay_without_its_block_is_a_config_error(tmp_path: Path) -> None:
    with DdsCommand(_config(tmp_path)) as wired, pytest.raises(ConfigError) as refused:
        wired.relay()
    assert refused.value.key == "dds.relay"


def test_no_dds_block_is_a_config_error() -> None:
    with pytest.raises(ConfigError) as refused:
        DdsCommand(AppConfig.from_mapping({}))
    assert refused.value.key == "dds"


def test_the_files_audit_path_is_the_trail_when_dds_audit_is_not_set(tmp_path: Path) -> None:
    trail = tmp_path / "shared-audit.db"
    with DdsCommand(_config(tmp_path, audit={"path": str(trail)})) as wired:
        assert wired.audit is not None and Path(wired.audit.path) == trail
