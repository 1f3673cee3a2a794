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
background is killed afterwards.  A chain runs in one shell, so a later block can stop the
server an earlier one started (``kill $gateway``).  A last test follows the whole README in
order in one shell and one directory, as a reader does: each guide must stop its own servers.
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

from antireplay.state import open_store
from antireplay.state.sqlite import SqliteStore

README = Path(__file__).resolve().parents[2] / "README.md"
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


def run_blocks(blocks: list[Snippet], tmp_path: Path, coda: str = "true") -> tuple[int, str]:
    """Run ``blocks`` in order in one ``bash -e`` (shell variables carry over, as in a reader's
    terminal; a Python block runs as a command of that shell), then ``coda``, in a private
    network namespace; kill whatever is left in the background."""
    (tmp_path / ".venv").symlink_to(sys.prefix)
    lines = []
    for i, snippet in enumerate(blocks):
        if snippet.lang == "bash":
            lines.append(snippet.code)
        else:
            (tmp_path / f"snippet{i}.py").write_text(snippet.code)
            lines.append(f"{shlex.quote(sys.executable)} snippet{i}.py")
    (tmp_path / "readme.sh").write_text("\n".join(lines))
    driver = f"ip link set lo up && bash -e -o pipefail readme.sh && {coda}"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    output = tmp_path / "output.txt"
    with output.open("wb") as sink:
        proc = subprocess.Popen(
            ["unshare", "-rn", "sh", "-c", driver], cwd=tmp_path, env=env, stdout=sink,
            stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        try:
            code = proc.wait(timeout=600)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)  # what it left in the background
    return code, output.read_text(errors="replace")


@pytest.mark.parametrize("chain", chains(), ids=lambda c: f"README.md:{c[0].line}")
def test_snippet_runs_verbatim(chain: list[Snippet], tmp_path: Path) -> None:
    code, said = run_blocks(chain, tmp_path)
    where = f"README.md:{chain[0].line}"
    assert code == 0, f"{where} exited {code}:\n{said[-4000:]}"
    for wanted in (w for snippet in chain for w in snippet.expect):
        assert wanted in said, f"{where}: {wanted!r} not in:\n{said[-4000:]}"


def test_readme_followed_in_order_in_one_shell(tmp_path: Path) -> None:
    """A reader runs every block top to bottom in one terminal and one directory: each guide
    stops the servers it started (checked after each guide, naming it), so the next guide's
    server gets its port (a leftover would answer the next readiness wait, or hang the DDS
    guide's ``wait``), and nothing is left listening at the end."""
    blocks = []
    for chain in chains():
        where = f"README.md:{chain[0].line}"
        left = f'[ -z "$(jobs -pr)" ] || {{ echo "{where} left running:"; jobs -r; exit 1; }}'
        blocks += [*chain, Snippet(chain[0].line, "bash", left, ())]
    listening = "ss -Hltn > listening.txt && ! grep -q . listening.txt"
    code, said = run_blocks(blocks, tmp_path, coda=listening)
    left = (tmp_path / "listening.txt").read_text() if (tmp_path / "listening.txt").exists() else ""
    assert code == 0, f"exited {code}; still listening: {left!r}\n{said[-4000:]}"
    for wanted in (w for snippet in blocks for w in snippet.expect):
        assert wanted in said, f"{wanted!r} not in:\n{said[-4000:]}"


def test_readme_waits_for_readiness_in_bounded_loops_and_notes_the_upgrade() -> None:
    readme = README.read_text(encoding="utf-8")
    assert "until curl" not in readme
    assert readme.count("for i in $(seq 100); do curl -sf") == 2
    assert "**Upgrading:** a signed `cmd` `STOP` or `RESUME` is now SAFETY" in readme


def test_readme_states_the_sqlite_busy_timeout_a_configured_store_uses(tmp_path: Path) -> None:
    """The README's number for how long a command waits on a locked state file is the busy
    timeout of the store a configuration's ``sqlite:`` spec opens."""
    store = open_store(f"sqlite:{tmp_path / 'state.db'}")
    try:
        assert isinstance(store, SqliteStore)
        waits_ms = store._db.execute("PRAGMA busy_timeout").fetchone()[0]
    finally:
        store.close()
    text = " ".join(README.read_text(encoding="utf-8").split())
    assert f"SQLite's busy timeout, {waits_ms / 1000:g} s (fixed: no configuration knob)" in text
