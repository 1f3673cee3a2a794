"""docs/conformance.md stays true: each SDK case it lists names a conformance test that
exists, and each conformance test is listed."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
TABLE = HERE.parents[2] / "docs" / "conformance.md"
ROW = re.compile(r"^\| `(?P<sdk>[^`]+)` \| `(?P<ours>[^`]+)` \| (?P<verdict>[^|]+) \|", re.M)


def listed() -> list[tuple[str, str, str]]:
    return [(m["sdk"], m["ours"], m["verdict"].strip()) for m in ROW.finditer(TABLE.read_text())]


def collected() -> set[str]:
    """The conformance tests as pytest collects them, named relative to this directory."""
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
         str(HERE)], capture_output=True, text=True, check=True, cwd=HERE.parents[2],
    ).stdout  # fmt: skip
    prefix = str(HERE.relative_to(HERE.parents[2])) + "/"
    return {line.removeprefix(prefix) for line in out.splitlines() if line.startswith(prefix)}


def test_every_sdk_case_in_the_table_has_a_test_and_every_test_a_row() -> None:
    rows = listed()
    assert len(rows) >= 60, "the table lost its rows"
    sdk = [r[0] for r in rows]
    assert len(sdk) == len(set(sdk)), "an SDK case is listed twice"
    assert {r[2] for r in rows} <= {"pass", "documented difference"}
    tests = collected() - {
        f"{Path(__file__).name}::{test_every_sdk_case_in_the_table_has_a_test_and_every_test_a_row.__name__}"
    }
    named = {r[1] for r in rows}
    assert named - tests == set(), "the table names tests that do not exist"
    assert tests - named == set(), "conformance tests missing from the table"
