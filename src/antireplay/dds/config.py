"""The ``dds:`` block of the configuration, where it always was (:mod:`antireplay.config.dds`).

Theory of operation
-------------------
The model lives in the configuration layer with every other section; this module
re-exports it so ``antireplay.dds.config`` keeps importing.
"""

from __future__ import annotations

from antireplay.config.dds import (
    ALLOWED,
    MAX_AGE_S,
    MAX_DOMAIN_ID,
    MAX_FORWARD_S,
    RENAMED,
    DdsConfig,
    ReaderConfig,
    RelayConfig,
    WriterConfig,
    parse_udp,
)

__all__ = [
    "ALLOWED",
    "MAX_AGE_S",
    "MAX_DOMAIN_ID",
    "MAX_FORWARD_S",
    "RENAMED",
    "DdsConfig",
    "ReaderConfig",
    "RelayConfig",
    "WriterConfig",
    "parse_udp",
]
