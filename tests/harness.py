"""The test harness: gateway processes, free ports and direct reads of a gateway's state.

The package keeps only what ``antireplay demo`` runs
(:func:`antireplay.demo.start_gateway` and :func:`~antireplay.demo.stop_gateway`);
what tests need beyond it (a restartable process that remembers what it said on
stderr, ports for other servers, the SQLite seen-set read directly, polling for an
event under a deadline) lives here.
"""

from __future__ import annotations

import socket
import sqlite3
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from antireplay.demo import start_gateway, stop_gateway


def until(what: str, done: Callable[[], object], timeout: float = 30.0) -> None:
    """Poll ``done`` until it is truthy (an event the test brings about, under a deadline,
    never a timing guess); fail naming ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not done():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.005)


def free_port() -> int:
    """A loopback TCP port nothing listens on now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class GatewayProcess:
    """``antireplay serve`` as a real subprocess on loopback, restartable on its port."""

    config: Path
    port: int = field(default_factory=free_port)
    proc: subprocess.Popen[bytes] | None = None
    stderr_text: str | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout_s: float = 30.0) -> None:
        self.proc = start_gateway(self.config, self.port, timeout_s)

    def stop(self) -> None:
        """Graceful stop (uvicorn finishes in-flight requests); keeps what it said on stderr."""
        if self.proc is not None:
            self.stderr_text = stop_gateway(self.proc)
            self.proc = None


def state_rows(state: Path) -> int:
    """Rows in the seen-set of the SQLite store under ``state`` (read-only)."""
    db = sqlite3.connect(f"file:{state / 'state.db'}?mode=ro", uri=True)
    try:
        return int(db.execute("SELECT count(*) FROM seen").fetchone()[0])
    finally:
        db.close()
