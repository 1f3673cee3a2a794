"""Which build of the freshness window runs: the mypyc-compiled extension or its source.

Theory of operation
-------------------
``setup.py`` compiles :mod:`antireplay.window` with mypyc from its own, unchanged
source and writes the SHA-256 of that source next to the extension
(``window.sha256``).  The compiled build cuts the cost of
``ReplayCache.check`` to about a third; its behaviour is the source's, and the tests run
against both builds.

Python's import system would load an extension in preference to ``window.py``
even after ``window.py`` was edited (an editable install that was not rebuilt).
Running code that differs from the source a reviewer read is not acceptable, so
this module, imported first by the package, picks the build:

* ``ANTIREPLAY_PURE_PYTHON=1`` in the environment: the source, always;
* an extension whose recorded digest matches ``window.py``: the extension;
* an extension with no digest or a different one: the source, with a
  ``RuntimeWarning`` that says how to rebuild;
* no extension (a pure-Python build): the source.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import os
import sys
import warnings
from pathlib import Path
from types import ModuleType

PURE_ENV = "ANTIREPLAY_PURE_PYTHON"
WINDOW = "antireplay.window"
SOURCE = Path(__file__).with_name("window.py")


def choose(origin: Path, pure_requested: bool) -> str:
    """``"compiled"`` if the module at ``origin`` is a current extension, else ``"source"``."""
    if origin.suffix == ".py" or pure_requested:
        return "source"
    source = origin.with_name("window.py")
    if not source.exists():
        return "compiled"  # an extension-only install: nothing to compare against
    digest = origin.with_name("window.sha256")
    recorded = digest.read_text(encoding="ascii").strip() if digest.exists() else ""
    if recorded != hashlib.sha256(source.read_bytes()).hexdigest():
        warnings.warn(
            f"{origin.name} was not built from the current {source}; running the source. "
            "Rebuild with: pip install -e .",
            RuntimeWarning,
            stacklevel=2,
        )
        return "source"
    return "compiled"


def load_source(name: str) -> ModuleType:
    """Execute ``window.py`` as module ``name`` (the pure-Python build), whatever is installed."""
    spec = importlib.util.spec_from_file_location(name, SOURCE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    parent, _, child = name.rpartition(".")
    setattr(sys.modules[parent], child, module)  # as the import system does for submodules
    return module


def _select() -> str:
    loaded = sys.modules.get(WINDOW)
    if loaded is not None:  # imported before the package (a reload): report what runs
        return "source" if str(loaded.__file__).endswith(".py") else "compiled"
    spec = importlib.util.find_spec(WINDOW)
    assert spec is not None and spec.origin is not None
    build = choose(Path(spec.origin), os.environ.get(PURE_ENV) == "1")
    if build == "source":
        load_source(WINDOW)
    else:
        importlib.import_module(WINDOW)
    return build


#: ``"compiled"`` or ``"source"``: the build of :mod:`antireplay.window` this process runs.
IMPLEMENTATION = _select()
