"""Subprocess for the outbox tests: a SQLite store and an audit trail draining its outbox.

``argv``: the directory (``state.db``, ``audit.db``), the mode, then its arguments:

* ``accept N THREADS``: N accepted messages (commit, then its durable row) from THREADS
  threads; prints ``BATCHES <store batches> OPS <store operations>`` at the end.
* ``refuse N``: N refusal rows, each answered once written; prints ``BATCHES ...``.
* ``hang-forget N``: N accepted rows, then a durable drain that stops dead between the
  trail's commit and the outbox's delete (prints ``STOP``; the test kills it there).
* ``hang-refused``: one refusal row answered (prints ``ANSWERED``), then waits to be killed.
* ``race KEYS``: commit each of ``KEYS`` (comma-separated) and audit the ones it won;
  prints ``WON <key>`` for each.
* ``paired N CONCURRENCY [HANG]``: N accepted messages as the gateway takes them, entry
  and row ONE operation (``commit_with_row_async``) from an event loop, CONCURRENCY at a
  time; prints ``ANSWERED <key>`` as each is answered.  With ``HANG``: the row of message
  number HANG prints ``HANG`` and blocks inside its batch's transaction (killed there).
* ``paired-threads N THREADS [HANG]``: the same as the thread driver takes them
  (``commit_with_row``, blocking), from THREADS threads.

The audit writer runs on a manual clock: it never fsyncs the trail by time, only when asked.
"""

from __future__ import annotations

import asyncio
import sys
import threading
from collections.abc import Callable
from pathlib import Path

from antireplay.audit import AuditLog, AuditRow
from antireplay.audit.writer import stored_json
from antireplay.core.clock import ManualClock
from antireplay.core.window import Seen
from antireplay.state.sqlite import SqliteStore

NOW = 1_800_000_000.0


class HangingLog(AuditLog):
    """An audit writer that announces ``STOP`` and hangs before deleting from the outbox."""

    def _forget_point(self) -> None:
        sys.stdout.write("STOP\n")
        sys.stdout.flush()
        threading.Event().wait()  # killed here


def row(outcome: str, msg_id: str, code: str | None = None) -> AuditRow:
    return AuditRow(NOW, outcome, code, msg_type=1, sender="op",
                    sender_verified=outcome == "accepted", msg_id=msg_id)  # fmt: skip


def accept(store: SqliteStore, audit: AuditLog, key: str) -> bool:
    """An accepted message's two steps, as the receive core takes them."""
    if not store.commit(key, NOW + 30.0, NOW).recorded:
        return False
    audit.append(row("accepted", key))
    return True


async def paired(store: SqliteStore, n: int, concurrency: int, hang: int | None) -> None:
    """Accepted messages as the event-loop driver takes them: one operation each."""
    gate = asyncio.Semaphore(concurrency)

    async def one(index: int) -> None:
        key = f"p{index}"
        build = row_of(key, index == hang)
        async with gate:
            seen, put = await store.commit_with_row_async(key, NOW + 30.0, NOW, build)
        answered(key, seen, put)

    await asyncio.gather(*(one(i) for i in range(n)))


def row_of(key: str, hang: bool) -> Callable[[Seen], str | None]:
    """The row a paired commit puts for ``key``; ``hang``: announce and block inside the
    batch's transaction (killed there)."""

    def row_for(seen: Seen) -> str | None:
        if hang:
            sys.stdout.write("HANG\n")
            sys.stdout.flush()
            threading.Event().wait()  # killed here, inside the transaction
        return stored_json(row("accepted", key)) if seen.recorded else None

    return row_for


def answered(key: str, seen: Seen | Exception, put: int) -> None:
    if isinstance(seen, Seen) and seen.recorded and put:
        sys.stdout.write(f"ANSWERED {key}\n")
        sys.stdout.flush()


def paired_threads(store: SqliteStore, n: int, threads: int, hang: int | None) -> None:
    """Accepted messages as the thread driver takes them: one blocking operation each."""

    def client(t: int) -> None:
        for index in range(t, n, threads):
            key = f"p{index}"
            answered(key, *store.commit_with_row(key, NOW + 30.0, NOW, row_of(key, index == hang)))

    work = [threading.Thread(target=client, args=(t,)) for t in range(threads)]
    for thread in work:
        thread.start()
    for thread in work:
        thread.join()


def run_paired(store: SqliteStore, mode: str, args: list[str]) -> None:
    """``paired`` (an event loop) or ``paired-threads`` (threads): N, its concurrency, HANG."""
    n, concurrency = int(args[0]), int(args[1])
    hang = int(args[2]) if len(args) > 2 else None
    if mode == "paired":
        asyncio.run(paired(store, n, concurrency, hang))
    else:
        paired_threads(store, n, concurrency, hang)


def main() -> None:
    where, mode, args = Path(sys.argv[1]), sys.argv[2], sys.argv[3:]
    store = SqliteStore(where / "state.db")
    kind = HangingLog if mode == "hang-forget" else AuditLog
    audit = kind(where / "audit.db", clock=ManualClock(wall=NOW))
    audit.attach(store.outbox())
    if mode == "accept":
        n, threads = int(args[0]), int(args[1])

        def client(t: int) -> None:
            for i in range(n // threads):
                accept(store, audit, f"k{t}-{i}")

        work = [threading.Thread(target=client, args=(t,)) for t in range(threads)]
        for thread in work:
            thread.start()
        for thread in work:
            thread.join()
    elif mode == "refuse":
        for i in range(int(args[0])):
            audit.append_later(row("rejected", f"r{i}", "REPLAY_DETECTED")).result()
    elif mode == "hang-forget":
        for i in range(int(args[0])):
            accept(store, audit, f"h{i}")
        audit.drain()
    elif mode == "hang-refused":
        audit.append_later(row("rejected", "refused-1", "REPLAY_DETECTED")).result()
        sys.stdout.write("ANSWERED\n")
        sys.stdout.flush()
        threading.Event().wait()  # killed here
    elif mode in {"paired", "paired-threads"}:
        run_paired(store, mode, args)
    elif mode == "race":
        for key in args[0].split(","):
            if accept(store, audit, key):
                sys.stdout.write(f"WON {key}\n")
    committer = store.group_commit
    sys.stdout.write(f"BATCHES {committer.batches} OPS {committer.operations}\n")
    sys.stdout.flush()
    audit.close()
    store.close()


if __name__ == "__main__":
    main()
