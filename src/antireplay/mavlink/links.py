"""The router's vocabulary: link roles, links, refusals and counters.

Theory of operation
-------------------
Plain values shared by :mod:`.router` (which drives them), its wiring and the PQ link; no
I/O here.  A :class:`RouterLink` is a transport (:mod:`.endpoints`) with a **role**:

* ``vehicle``: the flight controller side (a serial port, SITL, a companion's
  mavlink-router).  Its frames are judged by the **outbound** guard (the vehicle
  key); they are "outbound".
* ``ground``: an untrusted ground link (radio, LTE, a GCS on the network).  Its
  frames must verify with the link's key, judged by that key's **inbound** guard.
* ``trusted``: a local tool that cannot sign (mavros, BlueOS, Cockpit,
  mavlink2rest, a script).  Its unsigned v2 frames are **signed on its behalf**
  with the vehicle key, the router's ``sign_link_id`` and a durable
  :class:`~antireplay.mavlink.signer.TimestampSource` (never repeats, even across
  restarts), then judged by the vehicle key's inbound guard like any frame.

Frames from a vehicle link are ``outbound``; from a ground or trusted link, ``inbound``
(:data:`INBOUND`, :data:`OUTBOUND`).  A refused frame is a :class:`FrameRefusal` (the
line an operator reads); :class:`RouterStats` counts what the router did.
"""

from __future__ import annotations

from collections import Counter, OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass, field

from antireplay.core.messages import StrEnum
from antireplay.mavlink.codec import claimed_source
from antireplay.mavlink.endpoints import Peer, Transport

INBOUND, OUTBOUND = "inbound", "outbound"  # towards the vehicle, from the vehicle
Location = tuple["RouterLink", Peer | None]


class Role(StrEnum):
    """What an endpoint is (module docstring)."""

    VEHICLE = "vehicle"
    TRUSTED = "trusted"
    GROUND = "ground"


@dataclass(eq=False)
class RouterLink:
    """One endpoint of the router: a transport, its role and its key (None: trusted)."""

    transport: Transport
    role: Role
    key: bytes | None = None
    max_peers: int = 8
    #: A trusted link the operator acknowledged on the network (not loopback or serial).
    network: bool = False
    #: Peers that authenticated, least recent first (a ``udpin`` or ``tcpin`` link's receivers).
    peers: OrderedDict[Peer, None] = field(default_factory=OrderedDict)

    @property
    def name(self) -> str:
        return self.transport.spec.text


@dataclass(frozen=True)
class FrameRefusal:
    """A dropped frame: where, the code, and why (the log line an operator reads)."""

    direction: str
    link: str
    code: str
    reason: str
    raw: bytes
    frames: int = 1  # a summary of the refusals behind a restart fence: how many
    #: Behind a restart fence, after the first on its link: a later summary says it (the
    #: log and the audit trail skip it; a hook that counts every refusal still sees it).
    folded: bool = False

    def __str__(self) -> str:
        if self.frames != 1:
            return (
                f"refused {self.frames} {self.direction} frames on {self.link}: "
                f"{self.code}: {self.reason}"
            )
        source = claimed_source(self.raw)
        claims = "" if source is None else f" claiming {source[0]}/{source[1]}"
        return f"refused {self.direction} frame on {self.link}{claims}: {self.code}: {self.reason}"


@dataclass
class RouterStats:
    """What the router did: per direction, per code, per accepted stream."""

    forwarded: Counter[str] = field(default_factory=Counter)
    dropped: Counter[str] = field(default_factory=Counter)  # "direction:CODE"
    #: Refusals the handler could not record (the audit trail is down): still dropped.
    unaudited: int = 0
    #: Timer ticks whose signer reservation failed (the store is down).
    timer_failures: int = 0
    #: Accepted frames per stream ``(link name, system, component, link id)``, bounded.
    streams: OrderedDict[tuple[str, int, int, int], int] = field(default_factory=OrderedDict)
    #: Ground stations ``(link name, peer, system)`` whose first authentication was logged.
    stations: OrderedDict[tuple[str, Peer | None, int], None] = field(default_factory=OrderedDict)


def same_station(owner: RouterLink, link: RouterLink) -> bool:
    """Whether ``link`` may use ids authenticated on ``owner``: it is that link, or a ground
    link with the same key (the station's other radio)."""
    return link is owner or (link.role is Role.GROUND and link.key == owner.key)


def receivers(link: RouterLink) -> Iterable[Peer | None]:
    """A fixed endpoint's one destination, or the peers that authenticated on it."""
    return (None,) if link.transport.fixed else list(link.peers)
