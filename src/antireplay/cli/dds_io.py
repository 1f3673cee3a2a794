"""What ``antireplay dds read`` and ``dds write`` say and wait for, beside their commands.

Theory of operation
-------------------
A reader states at start whether it is fenced (:func:`start_line`: until when, why, what
lifts it); while fenced, its refusals behind the fence fold into one line per second
(:class:`FenceFold`) instead of one per sample.  Accepted values print as text when they
are UTF-8 (:func:`shown`; a relayed announcement shows its payload and origin).  A writer
first answers the challenges of fresh readers that matched (:func:`answer_pending`,
bounded by ``--linger``) so its first sample already passes their fence, and with
``--stdin`` reads one sample per line while answering challenges between lines
(:func:`stdin_lines`).  Cyclone DDS is imported only when a command runs.
"""

from __future__ import annotations

import dataclasses
import os
import select
import sys
import time
from collections.abc import Callable, Iterator
from datetime import datetime, timezone
from typing import TYPE_CHECKING

import click

from antireplay.epochs.sealing import SampleVerdict, readable

if TYPE_CHECKING:
    from antireplay.dds.topics import SealedReader, SealedWriter
    from antireplay.wiring.dds import DdsCommand

#: Seconds between two summary lines of refusals behind the start fence.
FOLD_S = 1.0
#: A writer stops waiting for challenges this long after the last one it answered.
QUIET_S = 0.2
RESTART_FENCE = "restart_fence"


def _clock_text(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, timezone.utc).strftime("%H:%M:%SZ")


def start_line(reader: SealedReader, wired: DdsCommand) -> str:
    """The reader's first line: where it reads and whether it starts fenced, with why,
    until when and what lifts the fence."""
    head = f"reading {reader.topic_name} on domain {wired.domain_id}"
    verifier = reader.verifier
    if not verifier.fenced():
        return f"{head}; no start fence: its store ({wired.block.reader.store}) kept its history"
    until = verifier.restart_fence()
    left = max(0.0, until / 1e9 - time.time())
    spec = wired.block.reader.store
    why = (
        "the memory store holds nothing of earlier runs"
        if spec == "memory"
        else f"the store {spec} has no history (new, emptied or lost)"
    )
    return (
        f"{head}; FENCED until {_clock_text(until)} (+{left:.1f} s): {why}, so a sample "
        f"sealed before then may have been accepted by an earlier run and is refused; each "
        f"writer that answers this reader's challenge (writers answer as they write) passes at "
        f"once; a store kept across restarts (sqlite:PATH) or a state.anchor sets no fence"
    )


class FenceFold:
    """Counts the refusals behind the start fence; :meth:`report` prints one line per
    ``FOLD_S`` for them (what the fence is waiting for, and until when)."""

    def __init__(self, reader: SealedReader) -> None:
        self.reader, self.folded, self._next = reader, 0, time.monotonic() + FOLD_S

    def took(self, verdict: SampleVerdict) -> bool:
        """Whether ``verdict`` is folded (a refusal behind the fence), not printed."""
        if verdict.detail != RESTART_FENCE:
            return False
        self.folded += 1
        return True

    def report(self, now: float) -> None:
        if now < self._next:
            return
        self._next = now + FOLD_S
        if not self.folded:
            return
        verifier = self.reader.verifier
        state = (
            f"fenced until {_clock_text(verifier.restart_fence())}, awaiting a writer's answer "
            f"to this reader's challenge"
            if verifier.fenced()
            else "the fence has lifted"
        )
        click.echo(
            f"REFUSED MESSAGE_STALE restart_fence: {self.folded} sample(s) sealed within the "
            f"start fence ({state})"
        )
        self.folded = 0


def shown(verdict: SampleVerdict, *, relayed: bool = False) -> str:
    """The verdict's line; an accepted relayed announcement shows its payload and origin."""
    if not (relayed and verdict.accepted and isinstance(verdict.value, bytes)):
        return verdict.line()
    from antireplay.dds.relay import RelayedAnnouncement  # noqa: PLC0415 - the dds extra

    body = RelayedAnnouncement.decode(verdict.value)
    line = dataclasses.replace(verdict, value=readable(body.payload)).line()
    return f"{line} origin={body.origin_prefix.hex()} origin_epoch={body.origin_epoch}"


def answer_pending(writer: SealedWriter, linger_s: float) -> int:
    """Answer fresh readers' challenges before the first sample, for up to ``linger_s``: a
    fenced reader's challenge channel is discovered a moment after its topic reader, so
    the first half waits for anyone on that channel (none: no fenced reader, go); then
    challenges are answered until ``QUIET_S`` after the last.  Returns how many."""
    start = time.monotonic()
    deadline = start + linger_s
    answered, quiet_until = 0, deadline
    while time.monotonic() < min(deadline, quiet_until):
        if writer.challenge_peers() == 0 and time.monotonic() >= start + linger_s / 2:
            break
        got = writer.answer_challenges()
        if got:
            answered += got
            quiet_until = time.monotonic() + QUIET_S
        time.sleep(0.02)
    return answered


def stdin_lines(between: Callable[[], object], poll_s: float = 0.05) -> Iterator[str]:
    """The lines of stdin (UTF-8, newline dropped, blank lines skipped), calling
    ``between()`` at least every ``poll_s`` while none is waiting (a writer answers
    challenges then)."""
    fd, pending = sys.stdin.fileno(), b""
    while True:
        ready, _, _ = select.select([fd], [], [], poll_s)
        if not ready:
            between()
            continue
        chunk = os.read(fd, 65536)
        if not chunk:
            break
        pending += chunk
        *lines, pending = pending.split(b"\n")
        yield from (text for raw in lines if (text := raw.decode(errors="replace").rstrip("\r")))
    if pending.strip():
        yield pending.decode(errors="replace")


RELAYED_TOPIC = "antireplay/relayed"

__all__ = ["RELAYED_TOPIC", "FenceFold", "answer_pending", "shown", "start_line", "stdin_lines"]
