"""Ids bound to a ground station's link, while that station is live.

Theory of operation
-------------------
A ground link that authenticates a frame with its key binds the frame's ``(system,
component)`` to itself (and to ground links sharing its key: the station's other radio,
``same``).  While the owning link is **live** (an authenticated frame on it within
``idle_s``), a frame claiming those ids from any other link is refused by the router
(``SOURCE_BOUND``) before it is judged, and never moves a route.  The owner gone quiet
for ``idle_s`` (a radio that died, a station that left), the binding no longer holds: a
station that authenticates the ids on another link (LTE after the radio, a second
station joining later) takes them over, and the router logs the take-over once.  An
unauthenticated claim (a trusted link, signed on its behalf) never binds.

A station's system is bound too, for trusted claims only: while a station that
authenticated as system 255 is live, a trusted link cannot claim 255/0 or 255/191 and gain
a route (and copies) to that system.  A system the vehicle links announce is never bound
whole (a multi-component vehicle), and another key's ground station may use another
component of the same system (two stations, one system id).

Sans-I/O: links are opaque values, time is passed in (monotonic seconds); the caller holds
the lock.  Bounded: at most ``max_entries`` bindings (least recently used dropped) and one
time per link.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

L = TypeVar("L", bound=Hashable)
#: How long a station's link may stay quiet before its ids may move to another link.
BIND_IDLE_S = 5.0
ANY = -1  # the component of a whole-system binding


class Bindings(Generic[L]):
    """``(system, component)`` (and stations' systems) to the link that authenticated them."""

    def __init__(
        self, same: Callable[[L, L], bool], *, max_entries: int, idle_s: float = BIND_IDLE_S
    ) -> None:
        self.same, self.max_entries, self.idle_s = same, max_entries, idle_s
        self._owners: OrderedDict[tuple[int, int], L] = OrderedDict()
        self._heard: dict[L, float] = {}

    def quiet(self, link: L, now: float) -> float:
        """Seconds since ``link``'s last authenticated frame (infinite: never)."""
        heard = self._heard.get(link)
        return float("inf") if heard is None else now - heard

    def live_owner(
        self, link: L, system: int, component: int, now: float, *, trusted: bool
    ) -> L | None:
        """The live owner that refuses a claim of ``system/component`` from ``link``, if any
        (a trusted link's claim is also refused for any component of a bound station system)."""
        keys = [(system, component), (system, ANY)] if trusted else [(system, component)]
        for ids in keys:
            owner = self._owners.get(ids)
            if (
                owner is not None
                and not self.same(owner, link)
                and self.quiet(owner, now) < self.idle_s
            ):
                return owner
        return None

    def bind(
        self, link: L, system: int, component: int, now: float, *, whole_system: bool
    ) -> tuple[L, float] | None:
        """Record an authenticated frame of ``system/component`` on ``link``; the previous
        owner and how long it was quiet when the ids moved to another station, else None."""
        previous = self._owners.get((system, component))
        moved = None
        if previous is not None and not self.same(previous, link):
            moved = (previous, self.quiet(previous, now))
        self._heard[link] = now
        for ids in [(system, component), (system, ANY)] if whole_system else [(system, component)]:
            owner = self._owners.get(ids)
            if owner is None or not self.same(owner, link):
                self._owners[ids] = link
            self._owners.move_to_end(ids)
        while len(self._owners) > self.max_entries:
            self._owners.popitem(last=False)
        return moved
