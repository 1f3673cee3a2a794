"""``scripts/install-system-packages``: one line while apt-get works, its log's tail only
when it fails (a fake ``apt-get`` on a ``PATH`` where every tool is missing)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "install-system-packages"

FAKE_APT = """#!/bin/sh
i=0; while [ $i -lt 500 ]; do echo "Get:$i http://deb.debian.org/debian noise"; i=$((i+1)); done
[ -z "$APT_FAILS" ] || { echo "E: Unable to locate package $APT_FAILS"; exit 100; }
"""


def run_script(tmp_path: Path, fails: str = "") -> subprocess.CompletedProcess[str]:
    """The script as root (apt-get is only faked), none of its tools on ``PATH``."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    (bin_dir / "apt-get").write_text(FAKE_APT)
    (bin_dir / "apt-get").chmod(0o755)
    tail = shutil.which("tail")
    assert tail is not None
    (bin_dir / "tail").unlink(missing_ok=True)
    (bin_dir / "tail").symlink_to(tail)
    env = {"PATH": str(bin_dir), "TMPDIR": str(tmp_path), "APT_FAILS": fails}
    bash = shutil.which("bash")
    assert bash is not None and os.geteuid() == 0, "the script installs only as root"
    return subprocess.run(
        [bash, str(SCRIPT)], env=env, capture_output=True, text=True, timeout=60, check=False
    )


def test_a_quiet_install_is_one_line_and_keeps_apt_gets_log(tmp_path: Path) -> None:
    done = run_script(tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.count("\n") == 1 and done.stderr == "", done.stdout + done.stderr
    assert done.stdout.startswith("system packages: installing redis-server wrk strace curl")
    assert (tmp_path / "antireplay-apt.log").read_text().count("noise") == 1000  # update + install
    assert done.stdout.split(" (apt-get")[0].endswith(" softhsm2")  # its tokens: tests/keys


def test_a_failed_install_shows_the_end_of_apt_gets_log(tmp_path: Path) -> None:
    done = run_script(tmp_path, fails="chromium-driver")
    assert done.returncode == 1
    lines = done.stderr.splitlines()
    assert lines[0].startswith("system packages: apt-get failed; the end of "), done.stderr
    assert lines[-1] == "E: Unable to locate package chromium-driver" and len(lines) == 21
