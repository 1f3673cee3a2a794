"""Epoch-authenticated, replay-proof topics and announcements on Eclipse Cyclone DDS.

Theory of operation
-------------------
DDS itself accepts any sample from anyone on the domain, and a captured sample
published again is delivered again.  This package carries
:mod:`antireplay.epochs` over real DDS (Cyclone DDS, the ``antireplay[dds]``
extra) so an application sees only authentic, fresh samples:

* :mod:`~antireplay.dds.topics`: a :class:`SealedWriter` seals every sample
  with its own :class:`~antireplay.epochs.EpochSigner` (nonce prefix, strictly
  increasing epoch, HMAC); a :class:`SealedReader` opens it with an
  :class:`~antireplay.epochs.EpochVerifier` and hands over only what passed,
  giving every other sample a typed :class:`SampleVerdict` (counted, audited; the pure
  framing and judging are :mod:`antireplay.epochs.sealing`).  The
  MAC key is derived per (topic name, type name), so a sample moved to another
  topic does not verify; the instance key travels inside the MAC.
* :mod:`~antireplay.dds.relay`: an announcement relay in the role of a Cloud
  Discovery Service: it opens participants' sealed announcements and announces
  them again under its own service-name prefix, with its epoch persisted across
  restarts, and reports a second relay that uses the same service name.
* :mod:`~antireplay.dds.ping`: binding pings, small UDP datagrams sealed with
  the ping key; a peer address is learned only from an authentic, fresh ping.
* :mod:`~antireplay.dds.domain`: the domain configuration (loopback-only when
  asked), :mod:`~antireplay.dds.config` the ``dds:`` block of the CLI.

Importing this package does not import Cyclone DDS (``antireplay --help`` stays
fast and works without the extra); the names below load on first use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from antireplay.dds.domain import join_domain, loopback_xml
    from antireplay.dds.ping import PingListener, PingSender
    from antireplay.dds.relay import AnnouncementRelay, RelayedAnnouncement
    from antireplay.dds.topics import SealedReader, SealedWriter, Verdict
    from antireplay.dds.wire import SealedSample
    from antireplay.epochs.sealing import SampleVerdict

_HOMES = {
    "join_domain": "domain",
    "loopback_xml": "domain",
    "PingListener": "ping",
    "PingSender": "ping",
    "AnnouncementRelay": "relay",
    "RelayedAnnouncement": "relay",
    "SampleVerdict": "topics",
    "SealedReader": "topics",
    "SealedSample": "wire",
    "SealedWriter": "topics",
    "Verdict": "topics",
}

__all__ = [
    "AnnouncementRelay",
    "PingListener",
    "PingSender",
    "RelayedAnnouncement",
    "SampleVerdict",
    "SealedReader",
    "SealedSample",
    "SealedWriter",
    "Verdict",
    "join_domain",
    "loopback_xml",
]


def __getattr__(name: str) -> Any:
    """Load the Cyclone DDS-backed names on first use."""
    if name not in _HOMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"antireplay.dds.{_HOMES[name]}"), name)
