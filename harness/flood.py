"""A refusal flood over UDP loopback against a real command, until its trail has rotated.

:func:`flood_until_rotated` sends ``frames`` round-robin to a command's port until the
audit trail at ``audit`` has had ``segments`` rotated segments removed by retention (the
first one left beside it is numbered above ``segments``), or fails after ``timeout_s``;
:func:`trail_bytes` is what the whole trail holds on disk, every segment's WAL included.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Sequence
from pathlib import Path

from antireplay.audit.segments import bytes_of, rotated


def trail_bytes(audit: Path) -> int:
    """The live segment's bytes and every rotated one's, WAL files included."""
    return sum(bytes_of(file) for _, file in rotated(audit)) + bytes_of(audit)


def flood_until_rotated(
    port: int, frames: Sequence[bytes], audit: Path, segments: int, timeout_s: float = 60.0
) -> int:
    """Send ``frames`` to ``127.0.0.1:port`` until retention removed ``segments`` rotated
    segments of ``audit``; how many datagrams it took."""
    deadline = time.monotonic() + timeout_s
    sent = 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        while time.monotonic() < deadline:
            for frame in frames:
                sock.sendto(frame, ("127.0.0.1", port))
            sent += len(frames)
            kept = rotated(audit)
            if kept and kept[0][0] > segments:
                return sent
    raise AssertionError(f"{audit}: {segments} segments not removed after {sent} datagrams")
