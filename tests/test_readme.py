"""The README's snippets run as written.

Convention: every ```bash and ```python block is preceded by an HTML comment, either
``<!-- test: run -->`` (this test runs it verbatim) or ``<!-- test: manual (why) -->``
(hardware, another program, the install itself).  ``<!-- test: run; expect: A | B -->``
also requires each of A, B in its output; ``<!-- test: run after the block above -->``
runs a block after the runnable block before it, in the same directory, with what that one
left running (its gateway).  A block runs in a fresh directory holding only ``.venv`` (this
interpreter's environment), under ``bash -e -o pipefail`` or this Python, in a private
network namespace (``unshare -rn``, loopback up), so the fixed ports the README uses (8080,
DDS) cannot collide with anything else on the machine; whatever it left running in the
background is killed afterwards.
"""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

README = Path(__file__).resolve().parent.parent / "README.md"
FENCE = re.compile(r"^```(bash|python)$", re.MULTILINE)
MARKED = re.compile(
    r"<!-- test: (?P<mode>run(?P<after> after the block above)?|manual \([^)]*\))"
    r"(?:; expect: (?P<expect>.*?))? -->\n"
    r"```(?P<lang>bash|python)\n(?P<code>.*?)^```$",
    re.MULTILINE | re.DOTALL,
)


@dataclass(frozen=True)
class Snippet:
    line: int
    lang: str
    code: str
    expect: tuple[str, ...]


def chains() -> list[list[Snippet]]:
    """The runnable blocks, each with the blocks that run after it."""
    text = README.read_text(encoding="utf-8")
    found: list[list[Snippet]] = []
    for match in MARKED.finditer(text):
        if not match["mode"].startswith("run"):
            continue
        expect = tuple(e.strip() for e in (match["expect"] or "").split("|") if e.strip())
        line = text.count("\n", 0, match.start("lang")) + 1
        snippet = Snippet(line, match["lang"], match["code"], expect)
        if match["after"]:
            found[-1].append(snippet)
        else:
            found.append([snippet])
    return found


def test_every_block_says_whether_it_is_run() -> None:
    text = README.read_text(encoding="utf-8")
    marked = {text.count("\n", 0, m.start("lang")) for m in MARKED.finditer(text)}
    fences = [text.count("\n", 0, m.start()) for m in FENCE.finditer(text)]
    unmarked = [n + 1 for n in fences if n not in marked]
    assert not unmarked, f"README.md lines {unmarked}: add <!-- test: run --> or manual (why)"


@pytest.mark.parametrize("chain", chains(), ids=lambda c: f"README.md:{c[0].line}")
def test_snippet_runs_verbatim(chain: list[Snippet], tmp_path: Path) -> None:
    (tmp_path / ".venv").symlink_to(sys.prefix)
    steps = []
    for i, snippet in enumerate(chain):
        script = tmp_path / (f"snippet{i}.sh" if snippet.lang == "bash" else f"snippet{i}.py")
        script.write_text(snippet.code)
        run = "bash -e -o pipefail" if snippet.lang == "bash" else shlex.quote(sys.executable)
        steps.append(f"{run} {script.name}")
    driver = " && ".join(["ip link set lo up", *steps])
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    output = tmp_path / "output.txt"
    with output.open("wb") as sink:
        proc = subprocess.Popen(
            ["unshare", "-rn", "sh", "-c", driver], cwd=tmp_path, env=env, stdout=sink,
            stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        try:
            code = proc.wait(timeout=300)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)  # what it left in the background
    said = output.read_text(errors="replace")
    where = f"README.md:{chain[0].line}"
    assert code == 0, f"{where} exited {code}:\n{said[-4000:]}"
    for wanted in (w for snippet in chain for w in snippet.expect):
        assert wanted in said, f"{where}: {wanted!r} not in:\n{said[-4000:]}"
