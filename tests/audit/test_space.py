"""Free space under the trail against its two floors, read at most once per ``ttl_s``."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from antireplay.audit.space import DiskSpace, Pressure
from antireplay.core.clock import ManualClock


def _free(path: Path) -> int:
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


def test_the_floors_give_the_pressure_and_the_reason(tmp_path: Path) -> None:
    free = _free(tmp_path)
    trail = tmp_path / "audit.db"
    assert DiskSpace(trail, min_free_bytes=1, refuse_free_bytes=0).pressure() is Pressure.OK
    low = DiskSpace(trail, min_free_bytes=free * 4, refuse_free_bytes=1)
    assert (low.pressure(), low.low(), low.reason()) == (Pressure.LOW, True, None)
    full = DiskSpace(trail, min_free_bytes=free * 4, refuse_free_bytes=free * 2)
    assert full.pressure() is Pressure.CRITICAL
    assert "audit_space.refuse_free_bytes" in str(full.reason())


def test_free_space_is_read_at_most_once_per_ttl(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    clock = ManualClock()
    space = DiskSpace(tmp_path / "audit.db", clock=clock, ttl_s=1.0)
    calls: list[str] = []
    real = os.statvfs

    def counted(path: str | Path) -> os.statvfs_result:
        calls.append(str(path))
        return real(path)

    monkeypatch.setattr(os, "statvfs", counted)
    for _ in range(100):
        space.free()
    assert len(calls) == 1
    clock.advance(1.0)
    space.free()
    assert len(calls) == 2


def test_a_filesystem_that_cannot_be_read_counts_as_full(tmp_path: Path) -> None:
    space = DiskSpace(tmp_path / "gone" / "audit.db", min_free_bytes=1, refuse_free_bytes=1)
    assert space.free() == 0 and space.pressure() is Pressure.CRITICAL


def test_the_second_floor_may_not_be_above_the_first(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="refuse_free_bytes"):
        DiskSpace(tmp_path / "audit.db", min_free_bytes=1, refuse_free_bytes=2)
