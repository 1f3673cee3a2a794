"""Free space under the audit trail, against two floors: disk pressure seen before it bites.

Theory of operation
-------------------
:class:`DiskSpace` reads the free bytes of the trail's filesystem (``os.statvfs``, what
an unprivileged writer may use: ``f_bavail``) at most once per ``ttl_s``, so a request
never pays for a system call, and compares them with two floors:

* below ``min_free_bytes`` the pressure is :attr:`Pressure.LOW`: refusals get no rows
  of their own and no summaries (still counted, :mod:`.refusals`), so what is left goes
  to accepted commands;
* below ``refuse_free_bytes`` it is :attr:`Pressure.CRITICAL`: the gateway refuses new
  commands with ``STATE_UNAVAILABLE`` (the reason says disk) and ``/readyz`` says why,
  before a full disk refuses them with an error nobody reads; a fresh authentic ESTOP
  still passes (its row spilled if the trail cannot take it, :mod:`.spill`).

A filesystem that cannot be read (the directory deleted) counts as no space at all.
"""

from __future__ import annotations

import enum
import os
import threading
from pathlib import Path

from antireplay.core.clock import Clock, resolve

MIB = 1024 * 1024
#: Below this many free bytes, refusals are only counted.
MIN_FREE_BYTES = 64 * MIB
#: Below this many free bytes, new commands other than a fresh ESTOP are refused.
REFUSE_FREE_BYTES = 16 * MIB
#: Seconds a free-space reading is trusted.
TTL_S = 1.0


class Pressure(enum.IntEnum):
    """How close the trail's filesystem is to full."""

    OK = 0
    LOW = 1
    CRITICAL = 2


class DiskSpace:
    """Cached free space of the filesystem holding ``path``, and its pressure level."""

    def __init__(
        self,
        path: str | Path,
        *,
        min_free_bytes: int = MIN_FREE_BYTES,
        refuse_free_bytes: int = REFUSE_FREE_BYTES,
        clock: Clock | None = None,
        ttl_s: float = TTL_S,
    ) -> None:
        if refuse_free_bytes > min_free_bytes:
            raise ValueError("refuse_free_bytes must not exceed min_free_bytes")
        self.path = Path(path)
        self.min_free_bytes, self.refuse_free_bytes = min_free_bytes, refuse_free_bytes
        self.clock, self.ttl_s = resolve(clock), ttl_s
        self._free = 0
        self._read_at: float | None = None
        self._lock = threading.Lock()

    def free(self) -> int:
        """Free bytes, read at most once per ``ttl_s``."""
        now = self.clock.monotonic()
        with self._lock:
            if self._read_at is None or now - self._read_at >= self.ttl_s:
                self._free, self._read_at = self._statvfs(), now
            return self._free

    def _statvfs(self) -> int:
        try:
            st = os.statvfs(self.path.parent if not self.path.is_dir() else self.path)
        except OSError:
            return 0
        return st.f_bavail * st.f_frsize

    def pressure(self) -> Pressure:
        free = self.free()
        if free < self.refuse_free_bytes:
            return Pressure.CRITICAL
        return Pressure.LOW if free < self.min_free_bytes else Pressure.OK

    def low(self) -> bool:
        """Below the first floor: refusals are counted, not written."""
        return self.pressure() >= Pressure.LOW

    def reason(self) -> str | None:
        """Why new commands are refused (below the second floor), else ``None``."""
        free = self.free()
        if free >= self.refuse_free_bytes:
            return None
        return (
            f"disk nearly full under the audit trail {self.path}: {free} bytes free, "
            f"below the floor of {self.refuse_free_bytes} (audit_space.refuse_free_bytes)"
        )


__all__ = ["MIN_FREE_BYTES", "REFUSE_FREE_BYTES", "DiskSpace", "Pressure"]
