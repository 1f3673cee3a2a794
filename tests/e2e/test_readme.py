"""The README's and the docs' snippets run as written, and the docs build as a site.

Convention, in README.md and every docs/**/*.md: every ```bash and ```python block is preceded
by an HTML comment, either ``<!-- test: run -->`` (this test runs it verbatim) or
``<!-- test: manual (why) -->`` (hardware, another program, the install itself).
``<!-- test: run; expect: A | B -->`` also requires each of A, B in its output;
``<!-- test: run after the block above -->`` runs a block after the runnable block before it in
the same file, in the same shell, with what that one left running (its gateway).  A block
runs in a fresh directory holding only ``.venv`` (this interpreter's environment, as a clone
holds it after the install; it is also ``HOME``, so a guide's scratch directory
``~/antireplay-try/...`` is the test's own), under
``bash -e -o pipefail`` or this Python, in a private network namespace (``unshare -rn``,
loopback up), so the fixed ports the docs use (8080, DDS) cannot collide with anything else on
the machine; whatever it left running in the background is killed afterwards.  A chain runs in
one shell, so a later block can stop the server an earlier one started (``kill $gateway``).
Per file, a last test follows the whole page in order in one shell and one directory, as a
reader does: each section must stop its own servers.

The blocks run the installed antireplay (``PYTHONPATH`` is dropped, as a reader has none);
``ANTIREPLAY_TEST_SRC=DIR`` runs them on the sources in DIR instead (a checkout's ``src``).
"""

from __future__ import annotations

import contextlib
import os
import re
import shlex
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import click
import pytest
import yaml

from antireplay.cli import main as cli
from antireplay.state import open_store
from antireplay.state.sqlite import SqliteStore

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
DOCUMENTS = [README, *sorted(DOCS.rglob("*.md"))]

FENCE = re.compile(r"^```(bash|python)$", re.MULTILINE)
MARKED = re.compile(
    r"<!-- test: (?P<mode>run(?P<after> after the block above)?|manual \([^)]*\))"
    r"(?:; expect: (?P<expect>.*?))? -->\n"
    r"```(?P<lang>bash|python)\n(?P<code>.*?)^```$",
    re.MULTILINE | re.DOTALL,
)


@dataclass(frozen=True)
class Snippet:
    where: str  # file:line, as a reader finds it
    lang: str
    code: str
    expect: tuple[str, ...]


def name(document: Path) -> str:
    return document.relative_to(ROOT).as_posix()


def chains(document: Path) -> list[list[Snippet]]:
    """The runnable blocks of ``document``, each with the blocks that run after it."""
    text = document.read_text(encoding="utf-8")
    found: list[list[Snippet]] = []
    for match in MARKED.finditer(text):
        if not match["mode"].startswith("run"):
            continue
        expect = tuple(e.strip() for e in (match["expect"] or "").split("|") if e.strip())
        where = f"{name(document)}:{text.count(chr(10), 0, match.start('lang')) + 1}"
        snippet = Snippet(where, match["lang"], match["code"], expect)
        if match["after"]:
            assert found, f"{where}: 'run after the block above' with no runnable block above"
            found[-1].append(snippet)
        else:
            found.append([snippet])
    return found


ALL_CHAINS = [chain for document in DOCUMENTS for chain in chains(document)]
RUNNABLE = [document for document in DOCUMENTS if chains(document)]


@pytest.mark.parametrize("document", DOCUMENTS, ids=name)
def test_every_block_says_whether_it_is_run(document: Path) -> None:
    text = document.read_text(encoding="utf-8")
    marked = {text.count("\n", 0, m.start("lang")) for m in MARKED.finditer(text)}
    fences = [text.count("\n", 0, m.start()) for m in FENCE.finditer(text)]
    unmarked = [n + 1 for n in fences if n not in marked]
    assert not unmarked, f"{name(document)} lines {unmarked}: add <!-- test: run --> or manual"


def block_environment() -> dict[str, str]:
    """A reader's environment: no ``PYTHONPATH``, unless ``ANTIREPLAY_TEST_SRC`` names the
    sources to run instead of the installed ones."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if env.get("ANTIREPLAY_TEST_SRC"):
        env["PYTHONPATH"] = env["ANTIREPLAY_TEST_SRC"]
    return env


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
            script = shlex.quote(str(tmp_path / f"snippet{i}.py"))  # run where the shell is
            lines.append(f"{shlex.quote(sys.executable)} {script}")
    (tmp_path / "readme.sh").write_text("\n".join(lines))
    driver = f"ip link set lo up && bash -e -o pipefail readme.sh && {coda}"
    output = tmp_path / "output.txt"
    with output.open("wb") as sink:
        proc = subprocess.Popen(
            ["unshare", "-rn", "sh", "-c", driver], cwd=tmp_path,
            env={**block_environment(), "HOME": str(tmp_path)},
            stdout=sink, stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        try:
            code = proc.wait(timeout=600)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)  # what it left in the background
    return code, output.read_text(errors="replace")


@pytest.mark.parametrize("chain", ALL_CHAINS, ids=lambda c: c[0].where)
def test_snippet_runs_verbatim(chain: list[Snippet], tmp_path: Path) -> None:
    code, said = run_blocks(chain, tmp_path)
    where = chain[0].where
    assert code == 0, f"{where} exited {code}:\n{said[-4000:]}"
    for wanted in (w for snippet in chain for w in snippet.expect):
        assert wanted in said, f"{where}: {wanted!r} not in:\n{said[-4000:]}"


@pytest.mark.parametrize("document", RUNNABLE, ids=name)
def test_page_followed_in_order_in_one_shell(document: Path, tmp_path: Path) -> None:
    """A reader runs every block of a page top to bottom in one terminal and one directory:
    each section stops the servers it started (checked after each, naming it), so the next
    section's server gets its port (a leftover would answer the next readiness wait, or hang
    the DDS guide's ``wait``), and nothing is left listening at the end."""
    blocks = []
    for chain in chains(document):
        where = chain[0].where
        left = f'[ -z "$(jobs -pr)" ] || {{ echo "{where} left running:"; jobs -r; exit 1; }}'
        blocks += [*chain, Snippet(where, "bash", left, ())]
    listening = "ss -Hltn > listening.txt && ! grep -q . listening.txt"
    code, said = run_blocks(blocks, tmp_path, coda=listening)
    left = (tmp_path / "listening.txt").read_text() if (tmp_path / "listening.txt").exists() else ""
    assert code == 0, f"exited {code}; still listening: {left!r}\n{said[-4000:]}"
    for wanted in (w for snippet in blocks for w in snippet.expect):
        assert wanted in said, f"{wanted!r} not in:\n{said[-4000:]}"
    harness = {".venv", "readme.sh", "output.txt", "listening.txt", "antireplay-try"}
    written = {p.name for p in tmp_path.iterdir()} - harness
    assert {n for n in written if not n.startswith("snippet")} == set(), (
        f"{name(document)} wrote these into the clone, not its scratch directory: {written}"
    )


SECRETS_AND_STATE = [
    "operator.key.pem", "gcs.key.pem", "sub/vehicle-x.key.pem", "fleet.psk", "sdk-operator.key",
    ".mavproxy/signing.keys", "signing.keys", ".antireplay/state.db", "antireplay-try/tour/x",
]  # fmt: skip


def test_the_clone_ignores_what_the_guides_write() -> None:
    """A private key, a pre-shared key, MAVProxy's keys or a state file the guides write is
    never one ``git add -A`` from a commit, wherever in the clone a reader ran a block."""
    done = subprocess.run(
        ["git", "check-ignore", "--no-index", "-v", *SECRETS_AND_STATE],
        cwd=ROOT, capture_output=True, text=True, check=False,
    )  # fmt: skip
    ignored = {line.split("\t", 1)[1] for line in done.stdout.splitlines()}
    assert ignored == set(SECRETS_AND_STATE), f"not ignored: {set(SECRETS_AND_STATE) - ignored}"


def nav_pages(nav: object) -> Iterator[str]:
    """The page paths in mkdocs.yml's ``nav`` (lists of ``{title: page or section}``)."""
    if isinstance(nav, str):
        yield nav
    elif isinstance(nav, list):
        for item in nav:
            yield from nav_pages(item)
    elif isinstance(nav, dict):
        for value in nav.values():
            yield from nav_pages(value)


def test_every_docs_page_is_in_the_nav_and_the_site_builds(tmp_path: Path) -> None:
    """A page missing from the nav is unreachable on the site; a broken link or anchor, or a
    nav entry without its page, fails the strict build."""
    nav = yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))["nav"]
    pages = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")}
    assert pages - set(nav_pages(nav)) == set(), "add these pages to mkdocs.yml's nav"
    build = [sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(tmp_path)]
    done = subprocess.run(build, cwd=ROOT, capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    assert (tmp_path / "guides" / "rcan" / "index.html").exists()


def commands(group: click.Group, prefix: str) -> Iterator[str]:
    for command_name, command in group.commands.items():
        if isinstance(command, click.Group):
            yield from commands(command, f"{prefix} {command_name}")
        else:
            yield f"{prefix} {command_name}"


def test_every_command_is_in_the_cli_reference() -> None:
    reference = (DOCS / "cli.md").read_text(encoding="utf-8")
    assert isinstance(cli, click.Group)
    missing = [c for c in commands(cli, "antireplay") if f"`{c}`" not in reference]
    assert not missing, f"docs/cli.md lacks {missing}"


def test_readme_waits_for_readiness_in_bounded_loops_and_notes_the_upgrade() -> None:
    readme = "\n".join(page.read_text(encoding="utf-8") for page in DOCUMENTS)
    assert "until curl" not in readme
    assert readme.count("for i in $(seq 100); do curl -sf") >= 2  # each wait a bounded loop
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
    text = " ".join(" ".join(d.read_text(encoding="utf-8") for d in DOCUMENTS).split())
    assert f"SQLite's busy timeout, {waits_ms / 1000:g} s (fixed: no configuration knob)" in text
