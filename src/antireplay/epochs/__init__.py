"""Epoch-authenticated announcements and binding pings (DDS discovery style), failing closed.

Theory of operation
-------------------
Four modules, one direction of imports:

* :mod:`~antireplay.epochs.policy` is the pure core: the sealed frame, its per-kind HKDF
  keys, prefixes and successors, and :class:`EpochPolicy`, which judges values and a time
  against its in-memory marks and returns typed refusals, admissions and events.  It
  touches no file, store, audit trail, log, clock or lock.
* :mod:`~antireplay.epochs.sealing` is pure too: a sealed topic's key, sample framing and
  the verdict on one sample (the DDS topics drive it).
* :mod:`~antireplay.epochs.signer` seals with strictly increasing, wall-anchored epochs,
  crash-safe through a durable state file, rotating its prefix after a forward glitch.
* :mod:`~antireplay.epochs.verifier` drives the policy on a replay store: it reads and
  persists the state, serializes, logs and audits, and moves a mark only after the store
  write that backs it succeeded.

Importing this package registers the signer's state repair (``antireplay state repair``).
"""

from __future__ import annotations

from antireplay.epochs.policy import (
    COLLISION_HORIZON_NS,
    EPOCH_LIMIT,
    MAX_LEN,
    MIN_LEN,
    NONCE_LEN,
    OUTSTANDING,
    PREFIX_LEN,
    RECENT_PER_PREFIX,
    TAG_LEN,
    VERSION,
    Admission,
    Announcement,
    Claim,
    EpochPolicy,
    KeyRing,
    KeyRotation,
    Kind,
    PrefixCollision,
    Refused,
    SenderRotated,
    TooFarAhead,
    derive_key,
    parse,
    prefix_for_service,
    successor_prefix,
)
from antireplay.epochs.signer import EpochSigner, signer_state
from antireplay.epochs.verifier import EpochVerifier

__all__ = [
    "COLLISION_HORIZON_NS",
    "EPOCH_LIMIT",
    "MAX_LEN",
    "MIN_LEN",
    "NONCE_LEN",
    "OUTSTANDING",
    "PREFIX_LEN",
    "RECENT_PER_PREFIX",
    "TAG_LEN",
    "VERSION",
    "Admission",
    "Announcement",
    "Claim",
    "EpochPolicy",
    "EpochSigner",
    "EpochVerifier",
    "KeyRing",
    "KeyRotation",
    "Kind",
    "PrefixCollision",
    "Refused",
    "SenderRotated",
    "TooFarAhead",
    "derive_key",
    "parse",
    "prefix_for_service",
    "signer_state",
    "successor_prefix",
]
