"""MAVLink router: many endpoints, each with a role; forwards what the guards accept.

Theory of operation
-------------------
A :class:`MavlinkRouter` joins :class:`~.links.RouterLink` s, each a transport with a role
(``vehicle``, ``ground``, ``trusted``: :mod:`.links`).  It holds no replay rule: a frame
goes through one guard call (:meth:`~.guard.MavlinkGuard.open`; two when a ground link has
its own key: its guard, then the vehicle key's on the frame signed again), and what a guard
refuses is a counted drop handed to ``on_reject`` (:class:`~.links.FrameRefusal`).  The
guard says what to sign on a trusted link's behalf (committed in the vehicle key's inbound
guard, so its capture is a replay on any link), refuses the router's ``sign_link_id`` from a
ground link (``WRONG_DIRECTION``: a reflected copy of a frame signed for a link with its own
key would be a new stream) and binds a system to its side; the router signs, forwards,
drops, counts and reports.  Frames travel in the vehicle key's form, signed again for a
ground link with its own key; unsigned allow-listed frames are never signed.

**Routing like mavlink-router**, learned only from authenticated frames: their (system,
component) route to the link and peer they came from (at most ``max_peers`` receivers per
link, the least recently authenticated dropped).  Untargeted frames go to every other link's
receivers, targeted ones where the target was seen, else to the vehicle side (from it:
``NO_ROUTE``); no receiver at all is ``NO_PEER`` (counted only).  Ids a ground link
authenticated are its own while it is live (:mod:`.binding`, ``SOURCE_BOUND``); refusals
behind a restart fence are folded (:mod:`.fencing`).  Decisions are made under one lock,
writes outside it (a slow TCP client stalls no other link); tables are bounded.  One timer
(:meth:`MavlinkRouter.tick`) claims and renews every guard's lease, flushes and reserves
signer timestamps; :meth:`MavlinkRouter.start` waits for every lease, then starts transports.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from antireplay.core.errors import (
    AntiReplayError,
    Code,
    InvalidFrameError,
    NonceExhaustedError,
    ReplayAttackError,
)
from antireplay.mavlink.binding import BIND_IDLE_S, Bindings
from antireplay.mavlink.codec import Frame, sign, target
from antireplay.mavlink.endpoints import Peer, Transport
from antireplay.mavlink.fencing import FENCE_SUMMARY_S, FenceFolds, until_text
from antireplay.mavlink.guard import MavlinkGuard, MavVerdict
from antireplay.mavlink.links import (
    INBOUND,
    OUTBOUND,
    FrameRefusal,
    Location,
    Role,
    RouterLink,
    RouterStats,
    receivers,
    same_station,
)
from antireplay.mavlink.policy import FrameAdmission, RestartFenceError
from antireplay.mavlink.signer import TimestampSource

log = logging.getLogger("antireplay.mavlink")
_CLAIM_RETRY_S = 0.05  # how often the timer tries a lease a crashed run still holds
SOURCE_BOUND = "SOURCE_BOUND"  # ids a ground station authenticated, claimed on another link
#: links.py's names, still importable from here
__all__ = ["FrameRefusal", "MavlinkRouter", "Role", "RouterLink", "RouterStats"]


class MavlinkRouter:
    """Routes frames between links, through the guards (module docstring).

    ``inbound`` maps each key a ground link (or the vehicle) uses to its inbound guard;
    ``signers`` each key the router signs with to its timestamp source.
    """

    def __init__(
        self,
        links: Sequence[RouterLink],
        inbound: Mapping[bytes, MavlinkGuard],
        outbound: MavlinkGuard,
        *,
        signers: Mapping[bytes, TimestampSource] | None = None,
        sign_link_id: int = 251,
        on_reject: Callable[[FrameRefusal], Any] | None = None,
        max_routes: int = 1024,
        max_stream_stats: int = 1024,
        bind_idle_s: float = BIND_IDLE_S,
    ) -> None:
        vehicle_keys = {link.key for link in links if link.role is Role.VEHICLE}
        vehicle_key = vehicle_keys.pop() if len(vehicle_keys) == 1 else None
        if vehicle_key is None:
            raise ValueError("the vehicle links need one key, the same for all")
        self.vehicle_key = vehicle_key
        for link in links:
            if link.role is Role.GROUND and link.key is None:
                raise ValueError(f"ground link {link.name} needs a key")
        missing = {self.vehicle_key} | {
            link.key for link in links if link.key and link.role is Role.GROUND
        }
        if missing - set(inbound):
            raise ValueError("every key in use needs an inbound guard")
        self.links = list(links)
        self.inbound, self.outbound = dict(inbound), outbound
        self.signers = dict(signers or {})
        self.sign_link_id = sign_link_id
        self.on_reject = on_reject
        self.max_routes, self.max_stream_stats = max_routes, max_stream_stats
        self.stats = RouterStats()
        self._by_transport = {id(link.transport): link for link in links}
        self._routes: OrderedDict[int, dict[int, Location]] = OrderedDict()
        #: ``(system, component)`` a live ground station authenticated with its key, to its link.
        self._bound: Bindings[RouterLink] = Bindings(
            same_station, max_entries=max_routes, idle_s=bind_idle_s
        )
        self._folds = FenceFolds(max_routes)
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._claimed = threading.Event()
        self._timer: threading.Thread | None = None

    def start(self, wait_s: float | None = None) -> None:
        """Start the timer, wait until every guard holds its lease (a crashed run's lease
        runs out on the wall clock: by default up to one lease and a second), then start
        every transport.  ``STATE_UNAVAILABLE`` if a lease stays held (another router)."""
        guards = self._guards()
        budget = max((2 * g.persist_interval_s + 1.25 for g in guards), default=0.0)
        self._stopping.clear()
        self._timer = threading.Thread(target=self._run_timer, daemon=True, name="mavlink timer")
        self._timer.start()
        if not self._claimed.wait(budget if wait_s is None else wait_s):
            try:
                for guard in guards:
                    if not guard.claimed:
                        guard.start()  # the last try: its refusal names the holder
            except ReplayAttackError:
                self._stop_timer()
                raise
        for link in self.links:
            link.transport.start(self._deliver)

    def stop(self) -> None:
        """Stop every transport and the timer, then flush every guard and release its lease."""
        for link in self.links:
            link.transport.close()
        self._stop_timer()
        self._summarise_fenced(self.outbound.clock.monotonic(), final=True)
        for guard in self._guards():
            guard.stop()

    def tick(self) -> None:
        """The router's timer, once per its period: every guard claims its lease or flushes
        and renews it (:meth:`MavlinkGuard.tick`), every signer reserves ahead."""
        for guard in self._guards():
            guard.tick_safely()
        for signer in self.signers.values():
            try:
                signer.tick()
            except ReplayAttackError:  # the store is down: the signing path fails closed
                self.stats.timer_failures += 1
        if all(guard.claimed for guard in self._guards()):
            self._claimed.set()
        self._summarise_fenced(self.outbound.clock.monotonic())

    def fence(self) -> tuple[float, str] | None:
        """While the router refuses frames stamped now: until when (wall seconds) and why
        (``lease``, ``high`` or ``lost``: :attr:`~antireplay.mavlink.policy.MavPolicy.fence_cause`),
        the latest of its guards' restart fences still ahead of the clock; else ``None``."""
        found = [fence for guard in self._guards() if (fence := guard.fenced_until())]
        return max(found) if found else None

    def _run_timer(self) -> None:
        """One timer for every guard and signer (no thread per guard): the router's period
        is its guards' shortest persist interval, a twentieth of a second while a lease is
        still to be claimed."""
        period = min((g.persist_interval_s for g in self._guards()), default=1.0)
        self.tick()
        while not self._stopping.wait(period if self._claimed.is_set() else _CLAIM_RETRY_S):
            self.tick()

    def _stop_timer(self) -> None:
        if self._timer is not None:
            self._stopping.set()
            self._timer.join()
            self._timer = None

    def routes(self) -> dict[tuple[int, int], str]:
        """The learned routes: ``(system, component)`` to the link's name."""
        with self._lock:
            return {
                (system, component): where[0].name
                for system, table in self._routes.items()
                for component, where in table.items()
            }

    def _guards(self) -> list[MavlinkGuard]:
        return [*self.inbound.values(), self.outbound]

    # --- the frame path --------------------------------------------------------------------

    def _deliver(
        self, transport: Transport, peer: Peer | None, frames: list[Frame], skipped: int
    ) -> None:
        link = self._by_transport[id(transport)]
        direction = OUTBOUND if link.role is Role.VEHICLE else INBOUND
        if skipped:
            self._refuse(
                direction,
                link,
                Code.INVALID_FRAME,
                f"{skipped} bytes that are not whole MAVLink frames",
                b"",
            )
        for frame in frames:
            if link.role is not Role.VEHICLE:
                with self._lock:
                    owner = self._bound.live_owner(
                        link, frame.sysid, frame.compid, self.outbound.clock.monotonic(),
                        trusted=link.role is Role.TRUSTED,
                    )  # fmt: skip
                if owner is not None:
                    self._refuse(
                        direction, link, SOURCE_BOUND,
                        f"system {frame.sysid} component {frame.compid} authenticated on "
                        f"{owner.name}: bound to that link while it is live, refused from "
                        "this one",
                        frame.raw,
                    )  # fmt: skip
                    continue
            try:
                verdict = self._judge(link, frame)
            except RestartFenceError as exc:
                self._fence_refused(direction, link, exc, frame)
                continue
            except ReplayAttackError as exc:
                self._refuse(direction, link, exc.code, exc.reason, frame.raw)
                continue
            aimed = target(verdict.frame)
            with self._lock:
                self._account(link, peer, verdict)
                self.stats.forwarded[direction] += 1
                targets = self._destinations(link, aimed)
            if not targets:
                if aimed[0]:
                    self._refuse(direction, link, "NO_ROUTE", "target never seen", frame.raw)
                else:  # telemetry before any receiver authenticated: counted, not logged
                    self.stats.dropped[f"{direction}:NO_PEER"] += 1
            for where, to in targets:
                self._send(where, to, verdict.frame)

    def _judge(self, link: RouterLink, frame: Frame) -> MavVerdict:
        """The guard's verdict on ``frame`` (module docstring); raises ReplayAttackError."""
        if link.role is Role.VEHICLE:
            return self.outbound.open(frame)
        key = self.vehicle_key if link.key is None else link.key  # None: a trusted link
        guard = self.inbound[key]
        trusted = link.role is Role.TRUSTED
        if (
            guard.admit(frame, trusted=trusted, own_link_id=self.sign_link_id)
            is FrameAdmission.SIGN
        ):
            frame = self._sign(frame, key)
        verdict = guard.open(frame)
        if key != self.vehicle_key and verdict.signed:  # a ground link with its own key
            return self.inbound[self.vehicle_key].open(self._sign(verdict.frame, self.vehicle_key))
        return verdict

    def _sign(self, frame: Frame, key: bytes) -> Frame:
        """``frame`` signed by the router with ``key``; a frame it cannot sign is refused."""
        signer = self.signers.get(key)
        if signer is None:
            raise InvalidFrameError("no timestamp source for this key: cannot sign")
        try:
            return sign(frame, key, self.sign_link_id, signer)
        except (ValueError, NonceExhaustedError) as exc:
            raise InvalidFrameError(f"cannot sign on behalf: {exc}") from None

    def _account(self, link: RouterLink, peer: Peer | None, verdict: MavVerdict) -> None:
        """Learn from an authenticated frame; count the stream (caller holds ``_lock``)."""
        frame = verdict.frame
        if verdict.signed:
            if link.role is Role.GROUND:
                self._greet(link, peer, frame.sysid)
                self._bind(link, frame)
            if peer is not None:
                link.peers[peer] = None
                link.peers.move_to_end(peer)
                link.transport.authenticated(peer)
                if len(link.peers) > link.max_peers:
                    link.peers.popitem(last=False)
            table = self._routes.setdefault(frame.sysid, {})
            table[frame.compid] = (link, peer)
            self._routes.move_to_end(frame.sysid)
            if len(self._routes) > self.max_routes:
                self._routes.popitem(last=False)
            others = [self.outbound] if link.role is not Role.VEHICLE else self.inbound.values()
            for guard in others:
                guard.bind_direction(verdict)
            key = (link.name, *verdict.stream)
            streams = self.stats.streams
            streams[key] = streams.get(key, 0) + 1
            streams.move_to_end(key)
            if len(streams) > self.max_stream_stats:
                streams.popitem(last=False)

    def _bind(self, link: RouterLink, frame: Frame) -> None:
        """Bind the ids a ground station authenticated with its key to its link (caller
        holds ``_lock``); its whole system unless the vehicle links announce that system."""
        vehicle = any(
            where[0].role is Role.VEHICLE for where in self._routes.get(frame.sysid, {}).values()
        )
        moved = self._bound.bind(
            link, frame.sysid, frame.compid, self.outbound.clock.monotonic(),
            whole_system=not vehicle,
        )  # fmt: skip
        if moved is not None:
            log.warning(
                "ids %d/%d moved from link %s (quiet %.1f s) to link %s, authenticated",
                frame.sysid, frame.compid, moved[0].name, moved[1], link.name,
            )  # fmt: skip

    def _greet(self, link: RouterLink, peer: Peer | None, system: int) -> None:
        """Log a ground station's first authenticated frame, once per station (bounded)."""
        station = (link.name, peer, system)
        stations = self.stats.stations
        if station in stations:
            stations.move_to_end(station)
            return
        stations[station] = None
        if len(stations) > self.max_routes:
            stations.popitem(last=False)
        where = (
            ""
            if peer is None
            else f" from {peer[0]}:{peer[1]}"
            if isinstance(peer, tuple)
            else f" (client {peer})"
        )
        log.info("%s: ground station system %d authenticated%s", link.name, system, where)

    def _destinations(
        self, source: RouterLink, aimed: tuple[int | None, int | None]
    ) -> list[Location]:
        """Where a frame with target ``aimed`` goes (module docstring); caller holds ``_lock``."""
        system, component = aimed
        if not system:
            return [
                (link, to) for link in self.links if link is not source for to in receivers(link)
            ]
        table = self._routes.get(system, {})
        seen = [where for where in table.values() if where[0] is not source]
        exact = table.get(component) if component else None
        if exact is not None and exact[0] is not source:
            seen = [exact]
        if seen:
            return _unique(seen)
        if source.role is Role.VEHICLE:
            return []
        return [
            (link, to) for link in self.links if link.role is Role.VEHICLE for to in receivers(link)
        ]

    def _send(self, link: RouterLink, to: Peer | None, frame: Frame) -> None:
        """Write the judged frame (signed again where ``link`` has a key of its own)."""
        data = frame.raw
        if frame.signed and link.key is not None and link.key != self.vehicle_key:
            try:
                data = self._sign(frame, link.key).raw
            except ReplayAttackError as exc:
                self._refuse(OUTBOUND, link, exc.code, exc.reason, frame.raw)
                return
        if not link.transport.send(data, to):
            direction = INBOUND if link.role is Role.VEHICLE else OUTBOUND
            self.stats.dropped[f"{direction}:UNREACHABLE"] += 1

    def _refuse(self, direction: str, link: RouterLink, code: str, reason: str, raw: bytes) -> None:
        self.stats.dropped[f"{direction}:{code}"] += 1
        self._report(FrameRefusal(direction, link.name, str(code), reason, raw))

    def _report(self, refusal: FrameRefusal) -> None:
        if self.on_reject is None:
            return
        try:
            self.on_reject(refusal)
        except AntiReplayError:  # an audit trail that is down must not stop the forwarding
            self.stats.unaudited += 1

    def _fence_refused(
        self, direction: str, link: RouterLink, exc: RestartFenceError, frame: Frame
    ) -> None:
        """Count a refusal behind the restart fence; report the first on a link at once, the
        rest marked ``folded`` and said by one line per ``FENCE_SUMMARY_S``
        (:meth:`_summarise_fenced`)."""
        self.stats.dropped[f"{direction}:{exc.code}"] += 1
        sender = (frame.sysid, frame.compid)
        now = self.outbound.clock.monotonic()
        if not self._folds.refused(
            direction, link.name, str(exc.code), sender, now, below_s=exc.below_s
        ):
            self._report(
                FrameRefusal(
                    direction, link.name, str(exc.code), exc.reason, frame.raw, folded=True
                )
            )
            return
        fence = self.fence()
        why = (
            f"fenced{until_text(fence, self.outbound.clock.wall())}"
            if fence is not None
            else f"the fence has passed by this router's clock: sender {sender[0]}/{sender[1]}'s"
            " clock is behind, or this is a capture"
        )
        self._report(
            FrameRefusal(
                direction, link.name, str(exc.code),
                f"{exc.reason}; {why}: further refusals behind the fence are "
                f"summarised every {FENCE_SUMMARY_S:g} s", frame.raw,
            )
        )  # fmt: skip

    def _summarise_fenced(self, now: float, *, final: bool = False) -> None:
        """Report the folded refusals behind the fence that are due (:mod:`.fencing`)."""
        wall = self.outbound.clock.wall()
        for line in self._folds.summaries(self.fence(), wall, now, final=final):
            self._report(
                FrameRefusal(line.direction, line.link, line.code, line.reason, b"", line.frames)
            )


def _unique(found: list[Location]) -> list[Location]:
    out: list[Location] = []
    for where in found:
        if not any(where[0] is w[0] and where[1] == w[1] for w in out):
            out.append(where)
    return out
