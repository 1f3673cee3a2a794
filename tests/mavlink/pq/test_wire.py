"""The PQ wire: what a ``PQ_REFUSAL``'s MAC covers."""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import pytest

from antireplay import ManualClock
from antireplay.mavlink.codec import parse_frame
from antireplay.mavlink.pq.wire import parse_refusal, refusal_frame
from antireplay.pq.session import Initiator, Responder

os.environ["MAVLINK20"] = "1"

from harness.pq_ends import GCS_KEY, ROBOT_KEM, STRANGER_KEY


@pytest.mark.parametrize(
    "change",
    [
        {"code": 3},
        {"reason": "HS1 signature does not verify "},
        {"reason": "message is 31.000s old; window is 30s"},
        {"transfer": 8},
        {"target": (254, 197)},
        {"target": (255, 198)},
        {"hs1_hash": bytes(8)},
    ],
)
def test_a_refusal_mac_covers_code_reason_transfer_and_target(
    clock: ManualClock, change: dict[str, Any]
) -> None:
    """Review 7b: a genuine refusal with any one field changed (the MAC kept) does not
    verify under the genuine key, so nobody can reword or redirect a real refusal."""
    hs1 = Initiator("gcs", STRANGER_KEY, clock).start(ROBOT_KEM.public_key())
    key = Responder(ROBOT_KEM, {"gcs": GCS_KEY.public_key()}, clock=clock).refusal_key(hs1)
    assert key is not None
    raw = refusal_frame(
        hs1, key, transfer=7, target=(255, 197), code=1,
        reason="HS1 signature does not verify", sysid=1, compid=197,
    )  # fmt: skip
    genuine = parse_refusal(parse_frame(raw))
    assert genuine.verify(hs1, key)
    assert not dataclasses.replace(genuine, **change).verify(hs1, key)
