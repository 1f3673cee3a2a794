"""MAVLink: the codec (frames, signing), the guard (the replay policy), the router.

This module only re-exports the public names; each concept lives in its own module:
:mod:`~antireplay.mavlink.codec` parses, frames and signs,
:mod:`~antireplay.mavlink.guard` judges frames (verify, bind, timestamp rules, commit,
the lease and restart fence), :mod:`~antireplay.mavlink.endpoints` reads connection
strings and moves bytes, and :mod:`~antireplay.mavlink.router` forwards what the
guards accept between vehicle, trusted and ground endpoints.
"""

from antireplay.mavlink.codec import (
    MAV_EPOCH,
    TS_LIMIT,
    UNITS_PER_S,
    Frame,
    FrameReader,
    TimestampSource,
    claimed_source,
    mav_time,
    parse_frame,
    passphrase_key,
    sign_frame,
    split_frames,
    target,
    target_system,
)
from antireplay.mavlink.endpoints import EndpointSpec, open_transport, parse_endpoint
from antireplay.mavlink.guard import MavlinkGuard, MavVerdict
from antireplay.mavlink.router import Link, MavlinkRouter, Refusal, Role, RouterStats

__all__ = [
    "MAV_EPOCH",
    "TS_LIMIT",
    "UNITS_PER_S",
    "EndpointSpec",
    "Frame",
    "FrameReader",
    "Link",
    "MavVerdict",
    "MavlinkGuard",
    "MavlinkRouter",
    "Refusal",
    "Role",
    "RouterStats",
    "TimestampSource",
    "claimed_source",
    "mav_time",
    "open_transport",
    "parse_endpoint",
    "parse_frame",
    "passphrase_key",
    "sign_frame",
    "split_frames",
    "target",
    "target_system",
]
