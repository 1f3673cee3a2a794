"""antireplay: stop captured, validly signed robot and drone commands from working twice.

This module only re-exports the public API; each concept lives in its own module.
``WINDOW_BUILD`` says whether the compiled or the source build of the window runs.
"""

from antireplay._native import IMPLEMENTATION as WINDOW_BUILD  # first: picks the window build
from antireplay.clock import Clock, ManualClock, SystemClock
from antireplay.config import SecurityConfig
from antireplay.errors import (
    AntiReplayError,
    Code,
    ConfigError,
    InvalidMessageIdError,
    InvalidTimestampError,
    MessageFromFutureError,
    MessageStaleError,
    NonceExhaustedError,
    ReplayAttackError,
    ReplayDetectedError,
)
from antireplay.messages import MessageType, SafetyEvent
from antireplay.replay import ReplayCache
from antireplay.window import Seen, Verdict, Window

__version__ = "0.1.0"

__all__ = [
    "WINDOW_BUILD",
    "AntiReplayError",
    "Clock",
    "Code",
    "ConfigError",
    "InvalidMessageIdError",
    "InvalidTimestampError",
    "ManualClock",
    "MessageFromFutureError",
    "MessageStaleError",
    "MessageType",
    "NonceExhaustedError",
    "ReplayAttackError",
    "ReplayCache",
    "ReplayDetectedError",
    "SafetyEvent",
    "SecurityConfig",
    "Seen",
    "SystemClock",
    "Verdict",
    "Window",
    "__version__",
]
