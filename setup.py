"""Build script: compiles the freshness window's hot path with mypyc, falling back to pure Python.

Everything else is declared in pyproject.toml.  ``antireplay.window`` is compiled from
its own, unchanged source (the same file the pure-Python fallback runs), which
roughly halves the cost of ``ReplayCache.check``.  Next to the extension the build
writes the SHA-256 of the source it compiled, so that at import time
:mod:`antireplay._native` can refuse a stale extension (an editable install whose
``window.py`` was edited after the build) and run the source instead.

Set ``ANTIREPLAY_PURE_PYTHON=1`` to skip compilation; a build machine without a C
compiler also ends up with the pure-Python package, with a warning.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path
from typing import Any

from setuptools import setup
from setuptools.command.build_ext import build_ext

HOT_MODULE = Path("src", "antireplay", "window.py")
PURE_ENV = "ANTIREPLAY_PURE_PYTHON"


class OptionalBuildExt(build_ext):
    """Build the mypyc extension if possible, and record the digest of its source."""

    def run(self) -> None:
        try:
            super().run()
        except Exception as exc:  # any compiler failure means: ship pure Python
            self.warn(f"antireplay: compiling {HOT_MODULE} failed ({exc}); using pure Python")
            return
        digest = hashlib.sha256(HOT_MODULE.read_bytes()).hexdigest()
        target = Path(self.get_ext_fullpath("antireplay.window")).with_name("window.sha256")
        target.write_text(digest + "\n", encoding="ascii")


def extensions() -> list[Any]:  # mypyc's stubs name distutils' Extension, setup() setuptools'
    if os.environ.get(PURE_ENV) == "1":
        return []
    try:
        from mypyc.build import mypycify  # noqa: PLC0415 - a build-only, optional dependency
    except ImportError:
        print("antireplay: mypyc is not available; building pure Python", file=sys.stderr)
        return []
    return mypycify([str(HOT_MODULE)], opt_level="3")


setup(ext_modules=extensions(), cmdclass={"build_ext": OptionalBuildExt})
