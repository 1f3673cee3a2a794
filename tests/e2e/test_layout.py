"""The house rules of the tree, checked mechanically: tests mirror modules, no test file
imports another, tests and benchmarks share only the process harness (``harness/``, at the
top of the checkout, importing neither), module docstrings carry no project history,
modules stay small or say why."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from harness import ROOT

SRC = ROOT / "src" / "antireplay"
TESTS = ROOT / "tests"
HARNESS = ROOT / "harness"
BENCHMARKS = ROOT / "benchmarks"
#: Suites about the whole system rather than one module.
CROSS_CUTTING = {"e2e", "conformance", "fuzz"}
#: A module longer than this says why in a docstring line starting with "Size:".
MAX_LINES = 500
TEST_MODULE = re.compile(r"^tests(\.\w+)*\.test_\w+$")
HISTORY = re.compile(r"\bissues?\s*#?\d+", re.IGNORECASE)


def every_test_file() -> list[Path]:
    return sorted(TESTS.rglob("test_*.py"))


def mirrors_a_module(test: Path) -> bool:
    """``tests/<pkg>/test_<name>.py`` for ``src/antireplay/<pkg>/<name>.py`` (or ``_<name>.py``,
    the subpackage ``<name>/``, the package ``<pkg>`` itself as ``test_<pkg>.py``), optionally
    narrowed to one aspect as ``test_<name>_<aspect>.py``; ``tests/test_init.py`` is the
    top-level ``__init__``."""
    package = SRC.joinpath(*test.parent.relative_to(TESTS).parts)
    stem = test.stem.removeprefix("test_")
    names = {p.stem.lstrip("_") for p in package.glob("*.py")} - {"init"}
    names |= {p.name for p in package.iterdir() if (p / "__init__.py").exists()}
    names |= {package.name} if package != SRC else {"init"}
    return any(stem == name or stem.startswith(name + "_") for name in names)


def test_every_test_file_mirrors_a_module_or_is_cross_cutting() -> None:
    stray = [
        str(test.relative_to(TESTS))
        for test in every_test_file()
        if test.relative_to(TESTS).parts[0] not in CROSS_CUTTING and not mirrors_a_module(test)
    ]
    assert stray == [], f"test files that mirror no module: {stray}"


def imported_modules(path: Path) -> set[str]:
    modules: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            modules |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:  # relative: resolved against the file's package
                package = path.relative_to(ROOT).parent.parts
                anchor = package[: len(package) - node.level + 1]
                module = ".".join([*anchor, *filter(None, [module])])
            modules.add(module)
            modules |= {f"{module}.{alias.name}" for alias in node.names}
    return modules


def test_no_test_file_imports_another() -> None:
    offenders = {
        str(path.relative_to(TESTS)): sorted(
            m for m in imported_modules(path) if TEST_MODULE.match(m)
        )
        for path in sorted(TESTS.rglob("*.py"))
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def importers_of(tree: Path, packages: set[str]) -> dict[str, list[str]]:
    """Files under ``tree`` that import a module of one of ``packages``, and what."""
    found = {
        str(path.relative_to(ROOT)): sorted(
            m for m in imported_modules(path) if m.split(".")[0] in packages
        )
        for path in sorted(tree.rglob("*.py"))
    }
    return {k: v for k, v in found.items() if v}


def test_tests_and_benchmarks_share_only_the_harness() -> None:
    """One process harness that both import; neither imports the other, and the harness
    imports neither (so a benchmark runs without the test suite and the other way round)."""
    assert (HARNESS / "__init__.py").is_file() and importers_of(TESTS, {"harness"})
    assert importers_of(BENCHMARKS, {"harness"}), "the benchmarks use the same harness"
    assert importers_of(TESTS, {"benchmarks"}) == {}
    assert importers_of(BENCHMARKS, {"tests"}) == {}
    assert importers_of(HARNESS, {"tests", "benchmarks"}) == {}


def test_helpers_live_in_the_harness() -> None:
    """Outside the cross-cutting suites (the fuzzer has its own runner), ``tests/`` holds
    only test files, ``conftest.py`` and package markers."""
    helpers = [
        str(path.relative_to(TESTS))
        for path in sorted(TESTS.rglob("*.py"))
        if path.relative_to(TESTS).parts[0] not in CROSS_CUTTING
        and not path.name.startswith("test_")
        and path.name not in {"conftest.py", "__init__.py"}
    ]
    assert helpers == [], f"helpers outside harness/: {helpers}"


def docstring(path: Path) -> str:
    return ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""


def test_no_module_docstring_tells_project_history() -> None:
    told = {
        str(path.relative_to(SRC)): HISTORY.findall(docstring(path))
        for path in sorted(SRC.rglob("*.py"))
    }
    assert {k: v for k, v in told.items() if v} == {}


def test_no_module_exceeds_the_size_limit_without_saying_why() -> None:
    oversized = {
        str(path.relative_to(SRC)): lines
        for path in sorted(SRC.rglob("*.py"))
        if (lines := len(path.read_text(encoding="utf-8").splitlines())) > MAX_LINES
        and not any(line.startswith("Size:") for line in docstring(path).splitlines())
    }
    assert oversized == {}, f"modules over {MAX_LINES} lines without a 'Size:' line: {oversized}"


def test_the_package_has_no_import_cycle() -> None:
    """Layers hold only if no module reaches itself through its imports (import-linter checks
    the direction between layers; this checks every pair of modules)."""
    import grimp  # noqa: PLC0415 - import-linter's graph builder, a dev dependency

    graph = grimp.build_graph("antireplay")
    cycles = sorted(
        {
            tuple(sorted((module, imported)))
            for module in graph.modules
            for imported in graph.find_modules_directly_imported_by(module)
            if graph.chain_exists(importer=imported, imported=module)
        }
    )
    assert cycles == [], f"import cycles: {cycles}"
