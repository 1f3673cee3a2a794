"""Configuration: one validated file for every command, a section per concern.

Theory of operation
-------------------
:class:`AppConfig` is the whole file (:mod:`~antireplay.config.app`): the sections every
command shares (:mod:`~antireplay.config.common`), the gateway's
(:mod:`~antireplay.config.gateway`), the router's and the PQ ends'
(:mod:`~antireplay.config.mavlink`) and the DDS commands' (:mod:`~antireplay.config.dds`).
:mod:`~antireplay.config.loader` reads the YAML and refuses a key where it does not
belong.  The ``security:`` block is the window policy's own settings
(:mod:`antireplay.core.settings`), re-exported here.  Values are named and checked here,
never opened: :mod:`antireplay.wiring` turns them into stores, trails and adapters.
"""

from __future__ import annotations

from antireplay.config.app import AppConfig
from antireplay.config.common import AnchorConfig, AuditConfig, AuditSpaceConfig, StateConfig
from antireplay.config.dds import DdsConfig
from antireplay.config.gateway import JwtConfig, KeyConfig
from antireplay.config.loader import load_yaml
from antireplay.config.mavlink import (
    MavlinkConfig,
    MavlinkPqConfig,
    MetricsConfig,
    PqGroundConfig,
    PqVehicleConfig,
)
from antireplay.core.settings import ALLOWED, SecurityConfig

__all__ = [
    "ALLOWED",
    "AnchorConfig",
    "AppConfig",
    "AuditConfig",
    "AuditSpaceConfig",
    "DdsConfig",
    "JwtConfig",
    "KeyConfig",
    "MavlinkConfig",
    "MavlinkPqConfig",
    "MetricsConfig",
    "PqGroundConfig",
    "PqVehicleConfig",
    "SecurityConfig",
    "StateConfig",
    "load_yaml",
]
