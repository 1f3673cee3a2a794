"""A small filesystem made by a test: a size-limited tmpfs in a mount namespace of its own.

:class:`SmallFs` keeps one holder process in a new user and mount namespace (``unshare
--user --map-root-user --mount``: no root needed) with a tmpfs of ``size`` mounted on
``mount``; :attr:`SmallFs.prefix` runs a command inside it (``nsenter``), and
:meth:`SmallFs.host` is where the test itself reads and writes the same files
(``/proc/<holder>/root/...``).  The namespace, and the tmpfs with it, go away with the
holder, so a failed test leaves no mount behind.
"""

from __future__ import annotations

import errno
import os
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class SmallFs:
    """A tmpfs of ``size`` bytes seen at ``mount`` by the commands run behind :attr:`prefix`."""

    def __init__(self, mount: Path, size: int) -> None:
        mount.mkdir(parents=True, exist_ok=True)
        self.mount = mount
        script = f"mount -t tmpfs -o size={size} tmpfs {mount} && echo up && exec sleep 86400"
        self.holder = subprocess.Popen(
            ["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", script],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        assert self.holder.stdout is not None
        said = self.holder.stdout.readline()
        assert said == "up\n", self.holder.stderr.read() if self.holder.stderr else said

    @property
    def prefix(self) -> tuple[str, ...]:
        """Run a command in the namespace where the tmpfs is mounted."""
        return ("nsenter", "-t", str(self.holder.pid), "-U", "-m", "--preserve-credentials")

    def host(self, name: str = "") -> Path:
        """``mount/name`` as this process reaches it (through the holder's root)."""
        return Path(f"/proc/{self.holder.pid}/root{self.mount}") / name

    def free(self) -> int:
        """Free bytes of the tmpfs, as the gateway inside sees them."""
        st = os.statvfs(self.host())
        return st.f_bavail * st.f_frsize

    def fill(self, leave: int, name: str = "filler") -> None:
        """Grow a filler file until about ``leave`` bytes are free (0: until full)."""
        fd = os.open(self.host(name), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
        try:
            for chunk in (65_536, 4096):
                while self.free() >= leave + chunk or (not leave and self.free()):
                    try:
                        os.write(fd, b"\0" * chunk)
                    except OSError as exc:
                        assert exc.errno == errno.ENOSPC
                        break
        finally:
            os.close(fd)

    def drain(self, name: str = "filler") -> None:
        """Give the filler's space back."""
        os.unlink(self.host(name))

    def close(self) -> None:
        self.holder.kill()
        self.holder.wait(timeout=10)


@contextmanager
def small_fs(mount: Path, size: int) -> Iterator[SmallFs]:
    """A :class:`SmallFs`, gone afterwards."""
    fs = SmallFs(mount, size)
    try:
        yield fs
    finally:
        fs.close()
