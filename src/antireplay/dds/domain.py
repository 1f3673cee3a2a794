"""Joining a DDS domain: one Cyclone domain per id per process, loopback-only on request.

Cyclone DDS reads its configuration per domain; :func:`join_domain` creates the
domain explicitly with an XML configuration (instead of the ``CYCLONEDDS_URI``
environment variable, which is process-wide), so tests can give every case its
own domain id and a loopback-only setup: the 127.0.0.1 interface, no
multicast, unicast discovery of peers at 127.0.0.1.
"""

from __future__ import annotations

import threading

try:
    from cyclonedds.domain import Domain, DomainParticipant
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ImportError("antireplay.dds needs Cyclone DDS: pip install 'antireplay[dds]'") from exc

#: Port arithmetic (7400 + 250 * id) caps the domain id well below 256.
MAX_DOMAIN_ID = 232
#: Participants per host a loopback domain can hold (each takes a unicast port pair).
MAX_PARTICIPANTS = 32

_lock = threading.Lock()
_domains: dict[int, Domain] = {}


def loopback_xml(domain_id: int) -> str:
    """A Cyclone configuration that keeps all traffic on 127.0.0.1."""
    return (
        f'<CycloneDDS><Domain id="{domain_id}"><General><Interfaces>'
        '<NetworkInterface address="127.0.0.1"/></Interfaces>'
        "<AllowMulticast>false</AllowMulticast></General><Discovery>"
        "<ParticipantIndex>auto</ParticipantIndex>"
        f"<MaxAutoParticipantIndex>{MAX_PARTICIPANTS}</MaxAutoParticipantIndex>"
        '<Peers><Peer address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>'
    )


def join_domain(domain_id: int, *, loopback: bool = True) -> DomainParticipant:
    """A new participant on ``domain_id``; the domain is configured on first join."""
    if not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise ValueError(f"domain_id must be 0..{MAX_DOMAIN_ID}, got {domain_id}")
    with _lock:
        if domain_id not in _domains:
            _domains[domain_id] = Domain(domain_id, loopback_xml(domain_id) if loopback else None)
    return DomainParticipant(domain_id)
