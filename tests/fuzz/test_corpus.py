"""Replays the fuzzing corpus (tests/corpus/<target>/) and the seeds through each target.

Every file is an input the coverage-guided fuzzer (``python -m tests.fuzz``) kept
because it reached new code, or a finding it made (``finding-*``), each fixed since.
The targets (tests/fuzz/targets.py) fail on any exception outside the typed
ReplayAttackError family and on any HTTP 5xx, so a regression in any parser
fails here on every run, without atheris.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.fuzz.targets import TARGETS, seeds

CORPUS = Path(__file__).parents[1] / "corpus"


@pytest.mark.parametrize("target", sorted(TARGETS))
def test_corpus_replays_without_untyped_errors(target: str) -> None:
    files = sorted((CORPUS / target).iterdir())
    if not files:
        pytest.fail(f"tests/corpus/{target}/ is empty: run python -m tests.fuzz {target}")
    check = TARGETS[target]
    for path in files:
        check(path.read_bytes())
    for seed in seeds(target):
        check(seed)


def test_findings_are_kept() -> None:
    """The fixed findings stay in the corpus (each failed on main before its fix)."""
    findings = {p.name for p in CORPUS.glob("*/finding-*")}
    assert {
        "finding-content-length-unicode-digits",
        "finding-msg-id-not-utf8",
        "finding-sig-kid-not-utf8",
        "finding-huge-timestamp",
        "finding-huge-timestamp-ms",
        "finding-huge-type",
    } <= findings
