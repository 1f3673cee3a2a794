"""Build script: compiles the replay hot path with mypyc, falling back to pure Python.

Everything else is declared in pyproject.toml.  The hot modules (the window policy,
the memory store and the ReplayCache that joins them, ``HOT_MODULES``) are compiled
from their own, unchanged sources (the same files the pure-Python fallback runs).
Next to each extension the build writes the SHA-256 of the source it compiled, so
that at import time :mod:`antireplay.core._native` can refuse a stale build (an editable
install whose sources were edited after the build) and run the sources instead.

mypyc runs inside ``build_ext`` only: pip imports this file several times (for its
build requirements and metadata), and type-checking on every import would triple
the install time.  Set ``ANTIREPLAY_PURE_PYTHON=1`` to skip compilation; a build
machine without a C compiler also ends up with the pure-Python package, with a
warning.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

HOT_MODULES = [
    Path("src", "antireplay", "core", "window.py"),
    Path("src", "antireplay", "state", "memory.py"),
    Path("src", "antireplay", "state", "replay.py"),
]
PURE_ENV = "ANTIREPLAY_PURE_PYTHON"
# While pip builds (build isolation) the third-party packages that window.py's own
# imports use may be absent: they are not on the compiled hot path, so they are
# typed Any, without the project's strict settings (CI runs mypy --strict itself),
# and only window.py's own type errors stop the compilation.
MYPYC_ARGS = [
    *map(str, HOT_MODULES),
    "--config-file=",
    "--ignore-missing-imports",
    "--follow-imports=silent",
]


class MypycBuildExt(build_ext):
    """Compile the hot modules with mypyc and record the digest of each source."""

    def finalize_options(self) -> None:
        # Runs once, when a build needs this command: swap the placeholder for mypyc's
        # extensions before setuptools annotates them.
        self.distribution.ext_modules = self._mypyc_extensions()
        super().finalize_options()

    def _mypyc_extensions(self) -> list[Any]:  # the stubs disagree on which Extension
        if os.environ.get(PURE_ENV) == "1":
            return []
        try:
            from mypyc.build import mypycify  # noqa: PLC0415 - a build-only dependency

            return mypycify(MYPYC_ARGS, opt_level="3")
        except (Exception, SystemExit) as exc:  # mypyc missing or failing: ship pure Python
            self._fall_back(exc)
            return []

    def _fall_back(self, exc: BaseException) -> None:
        self.warn(f"antireplay: not compiling the hot modules ({exc!r}); using pure Python")
        self.extensions = []
        self.distribution.ext_modules = []

    def run(self) -> None:
        if not self.extensions:
            return
        try:
            super().run()
        except Exception as exc:  # no C compiler, or it failed: ship pure Python
            self._fall_back(exc)
            return
        for source in HOT_MODULES:
            name = ".".join(source.with_suffix("").parts[1:])
            digest = hashlib.sha256(source.read_bytes()).hexdigest()
            target = Path(self.get_ext_fullpath(name)).with_name(f"{source.stem}.sha256")
            target.write_text(digest + "\n", encoding="ascii")


# A placeholder: it makes setuptools run build_ext and tag the wheel as
# platform-specific; MypycBuildExt swaps it for mypyc's real extensions.
PLACEHOLDER = Extension("antireplay.core.window", sources=[])

setup(ext_modules=[PLACEHOLDER], cmdclass={"build_ext": MypycBuildExt})
