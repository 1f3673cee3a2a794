"""MAVLink: the codec, the replay policy and its guard, signing timestamps, the router.

This module only re-exports the public names; each concept lives in its own module.
Pure (values and a time in, a decision out): :mod:`~antireplay.mavlink.codec` parses,
frames and signs, :mod:`~antireplay.mavlink.policy` judges frames (timestamp rules,
commit decisions, lease arithmetic), :mod:`~antireplay.mavlink.signing` hands out signing
timestamps.  Drivers: :mod:`~antireplay.mavlink.guard` runs the policy (verify, store I/O,
the lease and restart fence), :mod:`~antireplay.mavlink.signer` persists signing
timestamps, :mod:`~antireplay.mavlink.endpoints` reads connection
strings and moves bytes, and :mod:`~antireplay.mavlink.router` forwards what the
guards accept between vehicle, trusted and ground endpoints.
"""

from antireplay.mavlink.codec import (
    MAV_EPOCH,
    TS_LIMIT,
    UNITS_PER_S,
    Frame,
    FrameReader,
    claimed_source,
    mav_time,
    parse_frame,
    passphrase_key,
    sign_frame,
    split_frames,
    target,
    target_system,
)
from antireplay.mavlink.endpoints import EndpointSpec, is_local, open_transport, parse_endpoint
from antireplay.mavlink.guard import MavlinkGuard, MavVerdict
from antireplay.mavlink.policy import FrameAdmission, MavPolicy
from antireplay.mavlink.router import FrameRefusal, MavlinkRouter, Role, RouterLink, RouterStats
from antireplay.mavlink.signer import TimestampSource
from antireplay.mavlink.signing import SignTimestamps

#: The names these classes had before they were made unique across the package.
Admission, Link, Refusal = FrameAdmission, RouterLink, FrameRefusal

__all__ = [
    "MAV_EPOCH",
    "TS_LIMIT",
    "UNITS_PER_S",
    "Admission",
    "EndpointSpec",
    "Frame",
    "FrameAdmission",
    "FrameReader",
    "FrameRefusal",
    "Link",
    "MavPolicy",
    "MavVerdict",
    "MavlinkGuard",
    "MavlinkRouter",
    "Refusal",
    "Role",
    "RouterLink",
    "RouterStats",
    "SignTimestamps",
    "TimestampSource",
    "claimed_source",
    "is_local",
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
