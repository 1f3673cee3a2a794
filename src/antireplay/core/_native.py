"""Which build of the replay hot path runs: the mypyc-compiled extensions or their sources.

Theory of operation
-------------------
``setup.py`` compiles the hot modules (:data:`HOT`: the window policy, the memory
store, the ReplayCache) with mypyc from their own, unchanged sources and writes
the SHA-256 of each source next to its extension (``<module>.sha256``).  Their
behaviour is the sources'; the test suite runs the window and store tests
against both builds (``tests/core/test_native.py`` runs them again in a pure
process).

Python's import system would load an extension in preference to its ``.py``
even after the ``.py`` was edited (an editable install that was not rebuilt).
Running code that differs from the source a reviewer read is not acceptable, so
this module, imported first by the package, picks the build, all or nothing
(compiled modules rely on each other's native classes):

* ``ANTIREPLAY_PURE_PYTHON=1`` in the environment: the sources, always;
* every extension's recorded digest matches its source: the extensions;
* any extension with no digest or a different one: the sources, with a
  ``RuntimeWarning`` that says how to rebuild;
* no extensions (a pure-Python build): the sources.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.machinery
import importlib.util
import os
import sys
import warnings
from pathlib import Path
from types import ModuleType

PURE_ENV = "ANTIREPLAY_PURE_PYTHON"
#: The compiled modules, in import order (each may import the ones before it).
HOT = ("antireplay.core.window", "antireplay.state.memory", "antireplay.state.replay")
PACKAGE = Path(__file__).parent.parent


def source_of(name: str) -> Path:
    """The ``.py`` file of hot module ``name``."""
    return PACKAGE.joinpath(*name.split(".")[1:]).with_suffix(".py")


def choose(origin: Path, pure_requested: bool) -> str:
    """``"compiled"`` if the module at ``origin`` is a current extension, else ``"source"``."""
    if origin.suffix == ".py" or pure_requested:
        return "source"
    stem = origin.name.split(".", 1)[0]
    source = origin.with_name(f"{stem}.py")
    if not source.exists():
        return "compiled"  # an extension-only install: nothing to compare against
    digest = origin.with_name(f"{stem}.sha256")
    recorded = digest.read_text(encoding="ascii").strip() if digest.exists() else ""
    if recorded != hashlib.sha256(source.read_bytes()).hexdigest():
        warnings.warn(
            f"{origin.name} was not built from the current {source}; running the sources. "
            "Rebuild with: pip install -e .",
            RuntimeWarning,
            stacklevel=2,
        )
        return "source"
    return "compiled"


def origin_of(name: str) -> Path:
    """Where the import system would load hot module ``name`` from (without importing it)."""
    source = source_of(name)
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        candidate = source.with_name(source.stem + suffix)
        if candidate.exists():
            return candidate
    return source


def load_source(name: str) -> ModuleType:
    """Execute hot module ``name`` from its ``.py`` (the pure build), whatever is installed."""
    parent, _, child = name.rpartition(".")
    importlib.import_module(parent)
    spec = importlib.util.spec_from_file_location(name, source_of(name))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    setattr(sys.modules[parent], child, module)  # as the import system does for submodules
    return module


def _select() -> str:
    loaded = sys.modules.get(HOT[0])
    if loaded is not None:  # imported before the package (a reload): report what runs
        return "source" if str(loaded.__file__).endswith(".py") else "compiled"
    pure = os.environ.get(PURE_ENV) == "1"
    # Decide before importing anything: the stores package imports the window itself.
    if any(choose(origin_of(name), pure) == "source" for name in HOT):
        for name in HOT:
            load_source(name)
        return "source"
    for name in HOT:
        importlib.import_module(name)
    return "compiled"


#: ``"compiled"`` or ``"source"``: the build of the hot modules this process runs.
IMPLEMENTATION = _select()
