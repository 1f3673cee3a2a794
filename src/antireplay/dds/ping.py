"""Binding pings: small UDP control datagrams, sealed with the ping key, check then commit.

Theory of operation
-------------------
A participant tells a relay "I am reachable here" with a binding ping: an
:mod:`antireplay.epochs` frame of kind ``PING`` (its own HKDF key, so a ping
is never taken for an announcement nor the reverse) sent over UDP.  The
listener's order: datagram size (cheap, before any crypto), then
:meth:`EpochVerifier.open_ping` (MAC, freshness, the start fence and
``epoch > last``, then the commit on its store), and only then does it learn
the sender's address for that prefix.  A replayed
or forged ping from an attacker's address is refused with a typed verdict and
changes nothing: no address is learned from unauthenticated traffic.  Every
verdict is counted; refusals are audited at a bounded rate
(:class:`~antireplay.audit.RefusalAuditor`), and :meth:`PingListener.drain`
judges a bounded number of datagrams per call.
"""

from __future__ import annotations

import socket
from collections import Counter
from collections.abc import Callable

from antireplay.audit import AuditLog
from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import Code
from antireplay.dds.config import MAX_AGE_S, MAX_FORWARD_S
from antireplay.dds.topics import open_judged, record_refusal, refusal_auditor
from antireplay.epochs import MIN_LEN, EpochSigner, EpochVerifier, Kind
from antireplay.epochs.sealing import SampleVerdict
from antireplay.state import ReplayStore
from antireplay.state.durable import DurableState
from antireplay.state.memory import MemoryStore

#: A binding ping is small; anything larger is dropped before any crypto.
MAX_PING = 1024
#: Datagrams one :meth:`PingListener.drain` judges at most.
DRAIN_LIMIT = 256


class PingSender:
    """Seals binding pings and sends them over UDP (from 127.0.0.1 by default)."""

    def __init__(
        self,
        psk: bytes,
        *,
        nonce_prefix: bytes | None = None,
        state: DurableState | None = None,
        clock: Clock | None = None,
        bind: tuple[str, int] = ("127.0.0.1", 0),
        max_forward_s: float = MAX_FORWARD_S,
    ) -> None:
        self.signer = EpochSigner(psk, nonce_prefix=nonce_prefix, state=state,
                                  clock=clock, max_forward_s=max_forward_s)  # fmt: skip
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(bind)

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.sock.getsockname()
        return str(host), int(port)

    def ping(self, target: tuple[str, int], payload: bytes = b"") -> bytes:
        """Seal and send one ping; returns the datagram (what an attacker could capture)."""
        datagram = self.signer.seal_ping(payload)
        self.sock.sendto(datagram, target)
        return datagram

    def close(self) -> None:
        self.sock.close()


class PingListener:
    """Receives binding pings; learns a peer's address only from an authentic, fresh one."""

    def __init__(
        self,
        psk: bytes,
        *,
        bind: tuple[str, int] = ("127.0.0.1", 0),
        store: ReplayStore | None = None,
        clock: Clock | None = None,
        max_age_s: float = MAX_AGE_S,
        max_forward_s: float = MAX_FORWARD_S,
        audit: AuditLog | None = None,
        quiet: Callable[[], bool] | None = None,
    ) -> None:
        self._clock = resolve(clock)
        self.verifier = EpochVerifier(
            psk,
            store=MemoryStore(clock=self._clock) if store is None else store,
            namespace="dds:ping",
            max_age_s=max_age_s,
            max_forward_s=max_forward_s,
            clock=self._clock,
        )
        self.audit = audit
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(bind)
        self.peers: dict[bytes, tuple[str, int]] = {}
        self.counts: Counter[str] = Counter()
        self._refusals = refusal_auditor(self._clock, audit, self.counts, quiet)

    @property
    def address(self) -> tuple[str, int]:
        host, port = self.sock.getsockname()
        return str(host), int(port)

    def judge(self, datagram: bytes, source: tuple[str, int]) -> SampleVerdict:
        """Check, authenticate, commit one ping; ``instance`` is the source address."""
        where = f"{source[0]}:{source[1]}"
        if not MIN_LEN <= len(datagram) <= MAX_PING:
            verdict = SampleVerdict("malformed", Code.INVALID_FRAME, "bad ping length", where)
        else:
            opened = open_judged(self.verifier, datagram, Kind.PING, where)
            if isinstance(opened, SampleVerdict):
                verdict = opened
            else:
                self.peers[opened.nonce_prefix] = source
                verdict = SampleVerdict(
                    "accepted", None, "", where, opened.nonce_prefix, opened.epoch, opened.payload
                )
        self.counts[verdict.outcome] += 1
        if not verdict.accepted:
            record_refusal(self._refusals, verdict, "dds ping", self.counts)
        return verdict

    def receive(self, timeout_s: float) -> SampleVerdict | None:
        """Judge the next datagram, or None if none came within ``timeout_s``."""
        self.sock.settimeout(timeout_s)
        try:
            datagram, source = self.sock.recvfrom(MAX_PING + 1)
        except (TimeoutError, BlockingIOError):
            return None
        return self.judge(datagram, (str(source[0]), int(source[1])))

    def drain(self, limit: int = DRAIN_LIMIT) -> list[SampleVerdict]:
        """Judge the datagrams already waiting, at most ``limit``, without blocking: a
        flood cannot hold the caller's thread (the rest wait in the socket buffer, and
        the kernel drops what does not fit)."""
        verdicts: list[SampleVerdict] = []
        while len(verdicts) < limit and (verdict := self.receive(0.0)) is not None:
            verdicts.append(verdict)
        return verdicts

    def close(self) -> None:
        self._refusals.close()  # the folded refusals' summary rows
        self.sock.close()
