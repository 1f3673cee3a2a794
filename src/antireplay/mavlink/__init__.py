"""MAVLink v2: the codec (frames, signing), the guard (the replay policy) and the UDP proxy.

This module only re-exports the public names; each concept lives in its own module:
:mod:`~antireplay.mavlink.codec` parses and signs frames,
:mod:`~antireplay.mavlink.guard` judges them (verify, bind, timestamp rules, commit,
the lease and restart fence) and :mod:`~antireplay.mavlink.proxy` forwards what the
guards accept between a ground station and a vehicle.
"""

from antireplay.mavlink.codec import (
    MAV_EPOCH,
    TS_LIMIT,
    UNITS_PER_S,
    Frame,
    TimestampSource,
    claimed_source,
    mav_time,
    parse_frame,
    sign_frame,
    split_frames,
    target_system,
)
from antireplay.mavlink.guard import MavlinkGuard, MavVerdict
from antireplay.mavlink.proxy import MavlinkProxy, ProxyStats

__all__ = [
    "MAV_EPOCH",
    "TS_LIMIT",
    "UNITS_PER_S",
    "Frame",
    "MavVerdict",
    "MavlinkGuard",
    "MavlinkProxy",
    "ProxyStats",
    "TimestampSource",
    "claimed_source",
    "mav_time",
    "parse_frame",
    "sign_frame",
    "split_frames",
    "target_system",
]
