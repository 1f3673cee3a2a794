"""antireplay: stop captured, validly signed robot and drone commands from working twice.

Two layers, the way pyca/cryptography keeps its recipes apart from ``hazmat``:

**Recipes** (use these): each runs the whole receive path in the fixed order,
check (records nothing) → authenticate → commit (records), so nothing an
unauthenticated message carries changes state.

* :class:`Receiver` (:mod:`antireplay.rcan.receive`): RCAN envelopes over HTTP or
  any transport: shape, freshness, msg_id, signature, scope, commit, audit.
* :class:`Guard` / :class:`RcanGuard` (:mod:`antireplay.wiring`): the gateway's
  request path inside your own ASGI app, as middleware or a FastAPI dependency,
  handing the application a :class:`Verified` message and its signer.
* :class:`MavlinkGuard` (:mod:`antireplay.mavlink`): signed MAVLink v2 frames.
* :class:`Initiator` / :class:`Responder` (:mod:`antireplay.pq.session`):
  post-quantum sessions with counter windows.
* :class:`EpochSigner` / :class:`EpochVerifier` (:mod:`antireplay.epochs`):
  epoch-sealed announcements (DDS discovery style; :mod:`antireplay.dds` carries
  them over Cyclone DDS).

**Policies and primitives** (the lower layer: correct only when the caller
authenticates between ``check`` and ``commit``): :class:`ReplayCache` (its
``commit`` records whatever it is given), :class:`Window`, the counter
primitives :class:`NonceCounter`, :class:`CounterWindow`, :class:`NonceTracker`
and :class:`FencedTable`, and the stores (:func:`antireplay.state.open_store`).

Errors are data (:mod:`antireplay.core.errors`): every refusal is a
:class:`ReplayAttackError` whose :class:`Code` decides the HTTP status and NACK.

The recipes load on first use, so ``import antireplay`` stays light.
``WINDOW_BUILD`` says whether the compiled or the source build of the window runs.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from antireplay.core._native import IMPLEMENTATION as WINDOW_BUILD  # first: picks the window build
from antireplay.core.clock import Clock, ManualClock, SystemClock
from antireplay.core.counters import CounterWindow, FencedTable, NonceCounter, NonceTracker
from antireplay.core.errors import (
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
    WarningCode,
)
from antireplay.core.messages import MessageType, SafetyEvent
from antireplay.core.settings import SecurityConfig
from antireplay.core.window import Seen, Verdict, Window
from antireplay.rcan.envelope import safety_class
from antireplay.state.replay import ReplayCache

if TYPE_CHECKING:
    from antireplay.config import AppConfig
    from antireplay.epochs import EpochSigner, EpochVerifier
    from antireplay.http.guard import Verified
    from antireplay.mavlink import MavlinkGuard
    from antireplay.pq.session import Initiator, Responder
    from antireplay.rcan.receive import Receiver
    from antireplay.wiring import Guard, RcanGuard

__version__ = "0.1.0"

#: The recipes: name -> module, loaded on first use.
_RECIPES = {
    "Receiver": "antireplay.rcan.receive",
    "MavlinkGuard": "antireplay.mavlink",
    "Initiator": "antireplay.pq.session",
    "Responder": "antireplay.pq.session",
    "EpochSigner": "antireplay.epochs",
    "EpochVerifier": "antireplay.epochs",
    "Guard": "antireplay.wiring",
    "RcanGuard": "antireplay.wiring",
    "Verified": "antireplay.http.guard",
    "AppConfig": "antireplay.config",  # the gateway's whole file: AppConfig.from_yaml(path)
}

__all__ = [
    "WINDOW_BUILD",
    "AntiReplayError",
    "AppConfig",
    "Clock",
    "Code",
    "ConfigError",
    "CounterWindow",
    "EpochSigner",
    "EpochVerifier",
    "FencedTable",
    "Guard",
    "Initiator",
    "InvalidMessageIdError",
    "InvalidTimestampError",
    "ManualClock",
    "MavlinkGuard",
    "MessageFromFutureError",
    "MessageStaleError",
    "MessageType",
    "NonceCounter",
    "NonceExhaustedError",
    "NonceTracker",
    "RcanGuard",
    "Receiver",
    "ReplayAttackError",
    "ReplayCache",
    "ReplayDetectedError",
    "Responder",
    "SafetyEvent",
    "SecurityConfig",
    "Seen",
    "SystemClock",
    "Verdict",
    "Verified",
    "WarningCode",
    "Window",
    "__version__",
    "safety_class",
]


def __getattr__(name: str) -> Any:
    """Load a recipe on first use."""
    module = _RECIPES.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
