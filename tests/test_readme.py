"""The README's snippets run as written.

Convention: every ```bash and ```python block is preceded by an HTML comment, either
``<!-- test: run -->`` (this test runs it verbatim) or ``<!-- test: manual (why) -->``
(hardware, another program, the install itself).  ``<!-- test: run; expect: A | B -->``
also requires each of A, B in its output.  A block runs in a fresh directory holding only
``.venv`` (this interpreter's environment), under ``bash -e -o pipefail`` or this Python,
in a private network namespace (``unshare -rn``, loopback up), so the fixed ports the
README uses (8080, DDS) cannot collide with anything else on the machine; whatever it
left running in the background is killed afterwards.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

README = Path(__file__).resolve().parent.parent / "README.md"
FENCE = re.compile(r"^```(bash|python)$", re.MULTILINE)
MARKED = re.compile(
    r"<!-- test: (?P<mode>run|manual \([^)]*\))(?:; expect: (?P<expect>.*?))? -->\n"
    r"```(?P<lang>bash|python)\n(?P<code>.*?)^```$",
    re.MULTILINE | re.DOTALL,
)


@dataclass(frozen=True)
class Snippet:
    line: int
    lang: str
    code: str
    expect: tuple[str, ...]


def snippets() -> list[Snippet]:
    text = README.read_text(encoding="utf-8")
    found = []
    for match in MARKED.finditer(text):
        if match["mode"] != "run":
            continue
        expect = tuple(e.strip() for e in (match["expect"] or "").split("|") if e.strip())
        line = text.count("\n", 0, match.start("lang")) + 1
        found.append(Snippet(line, match["lang"], match["code"], expect))
    return found


def test_every_block_says_whether_it_is_run() -> None:
    text = README.read_text(encoding="utf-8")
    marked = {text.count("\n", 0, m.start("lang")) for m in MARKED.finditer(text)}
    fences = [text.count("\n", 0, m.start()) for m in FENCE.finditer(text)]
    unmarked = [n + 1 for n in fences if n not in marked]
    assert not unmarked, f"README.md lines {unmarked}: add <!-- test: run --> or manual (why)"


@pytest.mark.parametrize("snippet", snippets(), ids=lambda s: f"README.md:{s.line}")
def test_snippet_runs_verbatim(snippet: Snippet, tmp_path: Path) -> None:
    (tmp_path / ".venv").symlink_to(sys.prefix)
    script = tmp_path / ("snippet.sh" if snippet.lang == "bash" else "snippet.py")
    script.write_text(snippet.code)
    run = ["bash", "-e", "-o", "pipefail", script.name]
    if snippet.lang == "python":
        run = [sys.executable, script.name]
    isolated = ["unshare", "-rn", "sh", "-c", 'ip link set lo up && exec "$@"', "sh", *run]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    output = tmp_path / "output.txt"
    with output.open("wb") as sink:
        proc = subprocess.Popen(
            isolated, cwd=tmp_path, env=env, stdout=sink, stderr=subprocess.STDOUT,
            start_new_session=True,
        )  # fmt: skip
        try:
            code = proc.wait(timeout=300)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)  # what it left in the background
    said = output.read_text(errors="replace")
    assert code == 0, f"README.md:{snippet.line} exited {code}:\n{said[-4000:]}"
    for wanted in snippet.expect:
        assert wanted in said, f"README.md:{snippet.line}: {wanted!r} not in:\n{said[-4000:]}"
