"""The compiled window build is used only when it was built from the current source."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

import antireplay
from antireplay.core import _native

ROOT = Path(__file__).resolve().parents[2]


def test_installed_build_is_the_compiled_one_unless_pure_was_requested() -> None:
    # CI installs with the build's defaults, so a compiler failure or a stale
    # extension shows up here instead of as a silently slower window.
    pure = os.environ.get(_native.PURE_ENV) == "1"
    assert ("source" if pure else "compiled") == antireplay.WINDOW_BUILD
    assert antireplay.core.window.__file__ is not None
    assert antireplay.core.window.__file__.endswith(".py") == pure


def _extension(tmp_path: Path, source: bytes, recorded: str | None) -> Path:
    (tmp_path / "window.py").write_bytes(source)
    if recorded is not None:
        (tmp_path / "window.sha256").write_text(recorded + "\n", encoding="ascii")
    origin = tmp_path / "window.cpython-311-x86_64-linux-gnu.so"
    origin.write_bytes(b"\x7fELF")
    return origin


def test_current_extension_is_chosen(tmp_path: Path) -> None:
    origin = _extension(tmp_path, b"x = 1\n", hashlib.sha256(b"x = 1\n").hexdigest())
    assert _native.choose(origin, pure_requested=False) == "compiled"


@pytest.mark.parametrize("recorded", ["0" * 64, None])
def test_stale_or_unrecorded_extension_runs_the_source(
    tmp_path: Path, recorded: str | None
) -> None:
    origin = _extension(tmp_path, b"x = 2  # edited after the build\n", recorded)
    with pytest.warns(RuntimeWarning, match="Rebuild"):
        assert _native.choose(origin, pure_requested=False) == "source"


def test_pure_request_wins_over_a_current_extension(tmp_path: Path) -> None:
    origin = _extension(tmp_path, b"x = 1\n", hashlib.sha256(b"x = 1\n").hexdigest())
    assert _native.choose(origin, pure_requested=True) == "source"


def test_extension_only_install_is_used(tmp_path: Path) -> None:
    origin = tmp_path / "window.cpython-311-x86_64-linux-gnu.so"
    origin.write_bytes(b"\x7fELF")
    assert _native.choose(origin, pure_requested=False) == "compiled"


def test_pure_environment_switch_in_a_real_process() -> None:
    code = (
        "import antireplay, antireplay.core._native as n, sys\n"
        "hot = [sys.modules[m].__file__ for m in n.HOT]\n"
        "print(antireplay.WINDOW_BUILD, all(f.endswith('.py') for f in hot))\n"
    )
    env = {**os.environ, _native.PURE_ENV: "1"}
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.split() == ["source", "True"]


def test_window_and_store_tests_pass_on_the_pure_python_build() -> None:
    """The compiled and the source builds must not drift: run the same tests on the source."""
    tests = ["tests/core/test_window.py", "tests/e2e/test_window_model.py"]
    env = {**os.environ, _native.PURE_ENV: "1"}
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *tests],
        env=env, cwd=ROOT, capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert out.returncode == 0, out.stdout[-3000:]
    assert " passed" in out.stdout and "skipped" not in out.stdout
