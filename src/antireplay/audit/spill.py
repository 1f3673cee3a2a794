"""The ESTOP spill: a small reserved file for the rows of ESTOPs delivered while the trail failed.

Theory of operation
-------------------
Safety beats the audit trail: a fresh authentic ESTOP is delivered even when its row
cannot be written (full disk, trail deleted or replaced, a lock, an I/O error).  Its row
then goes here, and the writer merges it into the trail, chained like any other row,
with the next batch it commits (and at the next start), so the record is late, never
lost, not even across a restart.

The file is reserved when the trail opens: ``slots`` fixed-size slots of :data:`SLOT`
bytes, allocated with ``posix_fallocate``, so a spilled row is an in-place ``pwrite``
and ``fdatasync`` that needs no new block and holds on a really full disk.  Slot 0 is a
header with a random nonce; slot ``i`` holds row ``i`` as JSON with
``mac = HMAC(key, nonce | i | previous mac | row)``, under the trail's head key (kept
outside the trail), so a row cannot be forged, reordered or moved from another spill.
An empty slot ends the list.  Merged rows are cleared by a new header (new nonce) and the
rows not merged yet rewritten after it.  A crash between the merge and the clear merges
them twice: a duplicate row, never a lost one.  A spill whose header does not verify
under the key (the trail started afresh with a new key) is moved aside, kept as
evidence, and a new one reserved.

:func:`encode` and :func:`decode` are the format (no I/O); :class:`Spill` is the file.
"""

from __future__ import annotations

import hmac
import json
import logging
import os
import secrets
import threading
import time
from pathlib import Path
from typing import Any

from antireplay.core.errors import AuditFileError

#: Bytes of one slot: well inside a page, written in place.
SLOT = 512
#: Slots reserved (rows held) by default.
SLOTS = 1024
FORMAT = "antireplay-audit-spill"
log = logging.getLogger("antireplay.audit")


def _mac(key: bytes, nonce: str, index: int, prev: str, row: dict[str, Any] | None) -> str:
    body = json.dumps(row, sort_keys=True, separators=(",", ":"))
    text = f"antireplay/v1 audit spill|{nonce}|{index}|{prev}|{body}"
    return hmac.new(key, text.encode(), "sha256").hexdigest()


def _pad(body: dict[str, Any]) -> bytes:
    raw = json.dumps(body, sort_keys=True, separators=(",", ":")).encode()
    if len(raw) >= SLOT:
        raise ValueError(f"a spilled record takes {len(raw)} bytes, a slot {SLOT - 1}")
    return raw.ljust(SLOT - 1) + b"\n"


def header(key: bytes, nonce: str) -> bytes:
    """Slot 0: the format and the nonce the rows chain from."""
    return _pad({"format": FORMAT, "nonce": nonce, "mac": _mac(key, nonce, 0, "", None)})


def encode(key: bytes, nonce: str, index: int, prev: str, row: dict[str, Any]) -> tuple[bytes, str]:
    """Slot ``index`` holding ``row``, and its MAC (ValueError if it does not fit)."""
    mac = _mac(key, nonce, index, prev, row)
    return _pad({"i": index, "row": row, "mac": mac}), mac


def decode(
    key: bytes, nonce: str, index: int, prev: str, slot: bytes
) -> tuple[dict[str, Any], str] | None:
    """The row in slot ``index`` and its MAC; ``None`` for an empty slot; ValueError for a
    slot that is not a record written under ``key`` in this place."""
    if not slot.strip(b"\x00 \n"):
        return None
    body = json.loads(slot)
    if not isinstance(body, dict) or body.get("i") != index or not isinstance(body["row"], dict):
        raise ValueError(f"slot {index} is not a spilled row")
    if not hmac.compare_digest(str(body["mac"]), _mac(key, nonce, index, prev, body["row"])):
        raise ValueError(f"slot {index}: MAC does not verify")
    return body["row"], str(body["mac"])


class Spill:
    """The reserved file: rows appended durably in place, read back, cleared once merged."""

    def __init__(self, path: str | Path, key: bytes, *, slots: int = SLOTS) -> None:
        self.path, self.slots = Path(path), slots
        self._key = key
        self._lock = threading.Lock()
        self._rows: list[dict[str, Any]] = []
        self._fd = self._open()
        try:
            self._load()
        except BaseException:
            os.close(self._fd)
            raise

    def _open(self) -> int:
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        except OSError as exc:
            raise AuditFileError(
                str(self.path), f"cannot be opened ({exc.strerror})",
                recovery="free space or fix permissions where the audit trail lives",
            ) from None  # fmt: skip
        try:
            os.posix_fallocate(fd, 0, SLOT * (self.slots + 1))  # reserved now, used when full
        except OSError as exc:
            os.close(fd)
            raise AuditFileError(
                str(self.path), f"cannot be reserved ({exc.strerror})",
                recovery="free space where the audit trail lives",
            ) from None  # fmt: skip
        return fd

    def _load(self) -> None:
        """Read the header and the rows after it; a header of another key moves the file
        aside (evidence) and reserves a new one."""
        first = os.pread(self._fd, SLOT, 0)
        self._nonce = ""
        if first.strip(b"\x00 \n"):
            try:
                body = json.loads(first)
                nonce = str(body["nonce"])
                ok = body.get("format") == FORMAT and hmac.compare_digest(
                    str(body["mac"]), _mac(self._key, nonce, 0, "", None)
                )
            except (ValueError, KeyError, TypeError):
                ok = False
            if not ok:
                aside = self.path.with_name(f"{self.path.name}.unverified-{int(time.time())}")
                log.error("audit spill %s does not verify under the head key: moved to %s",
                          self.path, aside)  # fmt: skip
                os.rename(self.path, aside)
                os.close(self._fd)
                self._fd = self._open()
            else:
                self._nonce = nonce
        if not self._nonce:
            self._reset([])
            return
        prev = ""
        for index in range(1, self.slots + 1):
            try:
                found = decode(self._key, self._nonce, index, prev,
                               os.pread(self._fd, SLOT, index * SLOT))  # fmt: skip
            except ValueError as exc:
                log.error("audit spill %s: %s; the rows after it are not merged", self.path, exc)
                break
            if found is None:
                break
            row, prev = found
            self._rows.append(row)
        self._prev = prev

    def _reset(self, rows: list[dict[str, Any]]) -> None:
        """A new nonce, ``rows`` rewritten after it, the rest of the used slots zeroed."""
        used = len(self._rows)
        self._nonce, self._prev, self._rows = secrets.token_hex(16), "", []
        os.pwrite(self._fd, header(self._key, self._nonce), 0)
        for row in rows:
            self._write(row)
        blank = b"\x00" * SLOT
        for index in range(len(rows) + 1, used + 1):
            os.pwrite(self._fd, blank, index * SLOT)
        os.fdatasync(self._fd)

    def _write(self, row: dict[str, Any]) -> None:
        index = len(self._rows) + 1
        slot, mac = encode(self._key, self._nonce, index, self._prev, row)
        os.pwrite(self._fd, slot, index * SLOT)
        self._prev = mac
        self._rows.append(row)

    def add(self, row: dict[str, Any]) -> bool:
        """Spill one row durably; ``False`` if the file is full or cannot be written."""
        with self._lock:
            if len(self._rows) >= self.slots:
                return False
            try:
                self._write(row)
                os.fdatasync(self._fd)
            except (OSError, ValueError) as exc:
                log.error("audit spill %s cannot take a row: %s", self.path, exc)
                return False
            return True

    def pending(self) -> list[dict[str, Any]]:
        """The rows waiting to be merged, oldest first."""
        with self._lock:
            return list(self._rows)

    def merged(self, n: int) -> None:
        """The first ``n`` rows are durable in the trail: clear them."""
        with self._lock:
            self._reset(self._rows[n:])

    def close(self) -> None:
        os.close(self._fd)


__all__ = ["SLOT", "SLOTS", "Spill", "decode", "encode", "header"]
