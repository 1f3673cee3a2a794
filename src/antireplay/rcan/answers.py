"""Held answers: what a QoS retransmission gets back instead of a second execution.

Theory of operation
-------------------
An RCAN sender with ``qos`` >= 1 (the SDK's ``QoSManager``) resends the *identical*
signed message, same msg_id and signature, until it reads a COMMAND_ACK.  The
msg_id was spent when the first copy was committed, so the copy cannot run
again; if its answer was lost on the way back, the sender still needs it.

:class:`AnswerMemo` keeps, per msg_id accepted here from a message that declared
``qos`` >= 1, a :func:`digest` of its authenticated content (the signed bytes, the
signature's ``alg``, ``kid`` and value), its window expiry, the :class:`Signer`
that verified it and, once the transport produced it, the answer (status, headers,
body, already marked: ``"duplicate": true`` inserted into a JSON object body, its
other bytes untouched, and the header ``rcan-duplicate: true``).  A copy
whose digest equals the held one carries the same bytes under the same signature
as a message verified here, so it is exactly as authentic, with no second
signature check; it gets the held answer, which was on the wire already.

Bounded: at most ``capacity`` entries (the oldest forgotten first), a body larger
than :data:`MAX_BODY` is not held, at most :data:`MAX_TOTAL` body bytes in all, and
an entry past its window expiry is dropped (the window refuses the copy as stale
anyway).  Forgetting only means a copy gets ``REPLAY_DETECTED`` as before, never a
second execution.  An entry accepted but not yet answered is *in flight*: an event
loop may wait for it (:meth:`AnswerMemo.wait`, bounded); an entry dropped or
evicted wakes its waiters with ``None``.  Thread-safe; the lock is never held
across I/O or an await.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field

import msgspec

from antireplay.core.errors import InvalidEnvelopeError
from antireplay.rcan.auth import Signer
from antireplay.rcan.envelope import Envelope, canonical_bytes, sdk_signed_bytes

#: The largest body held for a retry (a larger answer: the retry gets 409).
MAX_BODY = 64 * 1024
#: All held bodies together (so ``capacity`` large answers cannot exhaust memory).
MAX_TOTAL = 32 * 1024 * 1024
#: The header marking a held answer sent again.
DUPLICATE_HEADER = ("rcan-duplicate", "true")
#: The audit ``warning`` (and the NACK ``detail``) of an answered retransmission.
QOS_RETRY = "QOS_RETRY"


@dataclass(frozen=True, slots=True)
class HeldAnswer:
    """An answer as the transport sends it again: status, headers, body bytes."""

    status: int
    headers: tuple[tuple[str, str], ...]
    body: bytes


def digest(env: Envelope, subset: bool) -> bytes | None:
    """Digest of what authenticated ``env``: the bytes its signature covers (the RCAN SDK's
    subset if ``subset``), the signature's alg, kid and value; ``None`` if it has no
    (well-formed) signature."""
    try:
        sig = env.signature()
    except InvalidEnvelopeError:  # a malformed sig block matches nothing
        return None
    if sig is None:
        return None
    signed = sdk_signed_bytes(env) if subset else canonical_bytes(env)
    h = hashlib.blake2b(digest_size=32)
    for part in (signed, sig.alg.encode(), sig.kid.encode(), sig.value.encode()):
        h.update(len(part).to_bytes(8, "big"))
        h.update(part)
    return h.digest()


def marked(status: int, headers: Iterable[tuple[str, str]], body: bytes) -> HeldAnswer:
    """The answer as a retransmission gets it: ``"duplicate": true`` inserted as the last
    key of a JSON object body (every other byte as the original; not re-encoded), and the
    ``rcan-duplicate: true`` header (all a non-JSON body gets)."""
    try:
        content = msgspec.json.decode(body)
    except msgspec.DecodeError:
        content = None
    if isinstance(content, dict) and content.get("duplicate") is not True:
        end = body.rstrip()
        inner = end[:-1].rstrip()  # a JSON object ends with "}"
        separator = b"" if inner.endswith(b"{") else b","
        body = inner + separator + b'"duplicate":true}' + body[len(end) :]
    kept = tuple((k, v) for k, v in headers if k.lower() != DUPLICATE_HEADER[0])
    return HeldAnswer(status, (*kept, DUPLICATE_HEADER), body)


_Waiter = tuple[asyncio.AbstractEventLoop, "asyncio.Future[HeldAnswer | None]"]


@dataclass(slots=True)
class Entry:
    """One accepted msg_id: its content digest, expiry, verifying signer, and answer."""

    digest: bytes
    subset: bool
    expires_at: float
    signer: Signer
    answer: HeldAnswer | None = None
    dropped: bool = False
    waiters: list[_Waiter] = field(default_factory=list)


def _wake(waiters: list[_Waiter], answer: HeldAnswer | None) -> None:
    for loop, future in waiters:
        with contextlib.suppress(RuntimeError):  # a closed loop has nobody left to answer
            loop.call_soon_threadsafe(_settle, future, answer)
    waiters.clear()


def _settle(future: asyncio.Future[HeldAnswer | None], answer: HeldAnswer | None) -> None:
    if not future.done():  # the waiter timed out or was cancelled
        future.set_result(answer)


class AnswerMemo:
    """msg_id -> :class:`Entry`, bounded (see the module docstring)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._entries: dict[str, Entry] = {}
        self._bytes = 0
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._entries)

    def expect(self, msg_id: str, entry: Entry, now: float) -> None:
        """Register an accepted message whose answer is still being produced."""
        with self._lock:
            self._drop_locked(msg_id)
            while self._entries and (
                len(self._entries) >= self.capacity
                or next(iter(self._entries.values())).expires_at < now
            ):
                self._drop_locked(next(iter(self._entries)))
            self._entries[msg_id] = entry

    def hold(
        self, msg_id: str, status: int, headers: Iterable[tuple[str, str]], body: bytes
    ) -> None:
        """The answer of an in-flight entry, kept :func:`marked` (a body larger than
        :data:`MAX_BODY`: the entry is forgotten); wakes whoever waits for it.  Costs
        nothing for a msg_id that is not in flight here (``qos`` 0)."""
        with self._lock:
            entry = self._entries.get(msg_id)
        if entry is None or entry.answer is not None:
            return
        answer = marked(status, headers, body) if len(body) <= MAX_BODY else None
        with self._lock:
            if self._entries.get(msg_id) is not entry or entry.answer is not None:
                return
            if answer is None or len(answer.body) > MAX_BODY:
                self._drop_locked(msg_id)
                return
            entry.answer = answer
            _wake(entry.waiters, answer)
            self._bytes += len(answer.body)
            while self._bytes > MAX_TOTAL:
                self._drop_locked(next(iter(self._entries)))

    def in_flight(self, msg_id: str) -> bool:
        """Whether ``msg_id`` waits for its answer here (accepted with ``qos`` >= 1)."""
        with self._lock:
            entry = self._entries.get(msg_id)
            return entry is not None and entry.answer is None

    def drop(self, msg_id: str) -> None:
        """Forget ``msg_id`` (its accept was refused after all); waiters get ``None``."""
        with self._lock:
            self._drop_locked(msg_id)

    def find(self, env: Envelope, now: float) -> Entry | None:
        """The entry of a message with ``env``'s msg_id and identical authenticated content
        within its window (held or in flight), else ``None``; no signature check."""
        msg_id = env.msg_id
        if type(msg_id) is not str:
            return None
        with self._lock:
            entry = self._entries.get(msg_id)
        if entry is None or entry.expires_at < now:
            return None
        found = digest(env, entry.subset)
        return entry if found is not None and hmac.compare_digest(found, entry.digest) else None

    async def wait(self, entry: Entry, timeout_s: float) -> HeldAnswer | None:
        """The entry's answer once the transport holds it; ``None`` if the entry is dropped
        or nothing arrives within ``timeout_s``.  Holds no thread."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[HeldAnswer | None] = loop.create_future()
        waiter = (loop, future)
        with self._lock:
            if entry.answer is not None:
                return entry.answer
            if entry.dropped:
                return None
            entry.waiters.append(waiter)
        try:
            return await asyncio.wait_for(future, timeout_s)
        except TimeoutError:
            return None
        finally:
            with self._lock, contextlib.suppress(ValueError):
                entry.waiters.remove(waiter)

    def _drop_locked(self, msg_id: str) -> None:
        entry = self._entries.pop(msg_id, None)
        if entry is None:
            return
        entry.dropped = True
        if entry.answer is not None:
            self._bytes -= len(entry.answer.body)
        _wake(entry.waiters, None)
