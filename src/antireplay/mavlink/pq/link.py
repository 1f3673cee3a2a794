"""The two post-quantum ends on the wire: each joins a local transport and an air transport.

Theory of operation
-------------------
A :class:`PqLink` moves bytes for one sans-I/O end of :mod:`antireplay.mavlink.pq`
between two :class:`~antireplay.mavlink.endpoints.Transport` s:

* **ground** (:class:`~antireplay.mavlink.pq.GroundEnd`): ``local`` is where the
  ground station and other plain-MAVLink tools connect (a ``udpin``: every peer that
  sends a frame receives the telemetry; this side is trusted, as a router's
  ``trusted`` link is), ``air`` the path to the vehicle (a radio, MAVProxy, a
  router).  It starts the handshake at :meth:`start`.
* **vehicle** (:class:`~antireplay.mavlink.pq.VehicleEnd`): ``local`` is the flight
  controller (serial, or a router's ``trusted`` endpoint, which signs for it with the
  MAVLink key), ``air`` the path to the ground.  A ``udpin`` air peer is learned only
  from a blob that authenticated (an accepted HS1 or an opened frame), as the router
  learns routes; plain MAVLink from the air never reaches the flight controller.

Every refusal is counted in :attr:`PqLink.dropped` under ``side:CODE`` and handed to
``on_reject`` as a :class:`~antireplay.mavlink.router.Refusal`, except plain MAVLink on
the air (routers send their own heartbeats there; never carried, counted ``air:PLAIN``);
what the end drops without an error (reassembly evictions and expiries, a ground end's
expired or displaced queued commands) is counted there too.  A vehicle end that
refuses a frame for a session it does not hold (``UNKNOWN_SESSION``,
``SESSION_CLOSED``) answers with the rate-limited ``PQ_STATUS`` hint.  Bytes written
to the air are counted (:attr:`PqLink.air_bytes`), and ``tap`` sees each air frame
(a capture, the bytes-on-air figures).  One lock serialises the end; writes happen
outside it.
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable
from typing import Any

from antireplay.core.errors import AntiReplayError, Code, ReplayAttackError
from antireplay.mavlink.endpoints import Peer, Transport
from antireplay.mavlink.pq.chunks import PlainFrameError
from antireplay.mavlink.pq.ends import GroundEnd, Output, VehicleEnd
from antireplay.mavlink.router import Refusal

_HINTED = {Code.UNKNOWN_SESSION, Code.SESSION_CLOSED}


class PqLink:
    """One end (ground or vehicle) between its local and its air transport."""

    def __init__(
        self,
        end: GroundEnd | VehicleEnd,
        local: Transport,
        air: Transport,
        *,
        on_reject: Callable[[Refusal], Any] | None = None,
        tap: Callable[[bytes], Any] | None = None,
        max_local_peers: int = 8,
    ) -> None:
        self.end, self.local, self.air = end, local, air
        self.on_reject, self.tap = on_reject, tap
        self.max_local_peers = max_local_peers
        self._dropped: Counter[str] = Counter()
        self.forwarded: Counter[str] = Counter()
        self.air_bytes = 0
        self._local_peers: dict[Peer, None] = {}
        self._air_peer: Peer | None = None
        self._lock = threading.Lock()
        self._count_lock = threading.Lock()

    def start(self) -> None:
        """Start both transports; a ground end sends its first handshake."""
        self.local.start(self._from_local)
        self.air.start(self._from_air)
        if isinstance(self.end, GroundEnd):
            with self._lock:
                frames = self.end.handshake()
            self._to_air(frames, None)

    def stop(self) -> None:
        self.local.close()
        self.air.close()

    def _from_local(
        self, transport: Transport, peer: Peer | None, frames: list[bytes], skipped: int
    ) -> None:
        if skipped:
            self._refuse("local", Code.INVALID_FRAME, f"{skipped} bytes that are no frame", b"")
        if peer is not None and peer not in self._local_peers:
            self._local_peers[peer] = None
            if len(self._local_peers) > self.max_local_peers:
                del self._local_peers[next(iter(self._local_peers))]
        for raw in frames:
            try:
                with self._lock:
                    air = self.end.from_local(raw)
            except ReplayAttackError as exc:
                self._refuse("local", exc.code, exc.reason, raw)
                continue
            self.forwarded["local"] += 1
            self._to_air(air, self._air_peer)

    def _from_air(
        self, transport: Transport, peer: Peer | None, frames: list[bytes], skipped: int
    ) -> None:
        if skipped:
            self._refuse("air", Code.INVALID_FRAME, f"{skipped} bytes that are no frame", b"")
        for raw in frames:
            hint: list[bytes] = []
            try:
                with self._lock:
                    out: Output = self.end.from_air(raw)
            except PlainFrameError:  # a router's own heartbeat, say: counted, not reported
                self._count("air:PLAIN")
                continue
            except ReplayAttackError as exc:
                self._refuse("air", exc.code, exc.reason, raw)
                if exc.code in _HINTED and isinstance(self.end, VehicleEnd):
                    with self._lock:
                        hint = self.end.hint()
                self._to_air(hint, peer)
                continue
            if out.authenticated:  # its sender is the air peer from now on
                self._air_peer = peer
                self.forwarded["air"] += 1
            for data in out.local:
                self._to_local(data)
            self._to_air(out.air, peer if out.authenticated else self._air_peer)

    def _to_local(self, data: bytes) -> None:
        peers: list[Peer | None] = [None] if self.local.fixed else list(self._local_peers)
        for peer in peers:
            if not self.local.send(data, peer):
                self._count("local:UNREACHABLE")

    def _to_air(self, frames: list[bytes], peer: Peer | None) -> None:
        if not frames:
            return
        if peer is None and not self.air.fixed:
            self._count("air:NO_PEER", len(frames))
            return
        for data in frames:
            if self.tap is not None:
                self.tap(data)
            self.air_bytes += len(data)
            if not self.air.send(data, peer):
                self._count("air:UNREACHABLE")

    @property
    def dropped(self) -> Counter[str]:
        """Everything dropped, by ``side:REASON``: refusals (``side:CODE``), what the end
        threw away without an error (reassembly: ``air:EVICTED``, ``air:EXPIRED``,
        ``air:DUPLICATE``; a ground end's local messages that never left:
        ``local:NO_SESSION``, ``local:QUEUE_FULL``, ``local:QUEUE_EXPIRED``), plain
        MAVLink on the air (``air:PLAIN``) and what could not be written."""
        with self._lock:
            stats = self.end.reassembly
            out = Counter(
                {
                    "air:EVICTED": stats.evicted,
                    "air:EXPIRED": stats.expired,
                    "air:DUPLICATE": stats.duplicates,
                }
            )
            if isinstance(self.end, GroundEnd):
                out.update({f"local:{k}": v for k, v in self.end.drops.items()})
        with self._count_lock:
            out.update(self._dropped)
        return +out  # the zero counts dropped

    def _count(self, key: str, n: int = 1) -> None:
        with self._count_lock:
            self._dropped[key] += n

    def _refuse(self, side: str, code: str, reason: str, raw: bytes) -> None:
        self._count(f"{side}:{code}")
        if self.on_reject is None:
            return
        try:
            self.on_reject(Refusal(side, f"pq {side}", str(code), reason, raw))
        except AntiReplayError:
            self._count("unaudited")
