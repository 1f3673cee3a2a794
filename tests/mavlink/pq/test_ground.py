"""The PQ ground end (the initiator): its handshake, queue, retries and rekeys."""

from __future__ import annotations

import os

import pytest

from antireplay import ManualClock
from antireplay.core.errors import (
    InvalidFrameError,
)
from antireplay.mavlink.pq import (
    REKEY_TRANSFERS,
    TRANSFER_LIMIT,
)

os.environ["MAVLINK20"] = "1"

from harness.pq_ends import EndPair, arm, connected, plain


def test_queued_commands_go_out_after_the_handshake(clock: ManualClock) -> None:
    link = EndPair(clock)
    hs1 = link.ground.from_local(arm())  # no session yet: queued, the handshake starts
    link.up(hs1)
    assert len(link.commands()) == 1


def test_heartbeats_do_not_push_a_queued_command_out(clock: ManualClock) -> None:
    link = EndPair(clock)
    hs1 = link.ground.from_local(arm())
    beat = plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4))
    for _ in range(50):
        link.ground.from_local(beat)
    link.up(hs1)
    assert len(link.commands()) == 1 and link.ground.unsent == 50


def test_queued_commands_expire_and_every_drop_is_counted(clock: ManualClock) -> None:
    link = EndPair(clock)
    for p in range(10):  # no vehicle: every HS1 is lost, commands queue
        link.ground.from_local(arm(param1=float(p)))
    assert link.ground.drops == {"QUEUE_FULL": 2}
    clock.advance(3)
    link.ground.from_local(arm(param1=10.0))
    clock.advance(3)  # all but the last are older than queue_ttl_s (5 s)
    link.up(link.ground.handshake())
    assert [c.param1 for c in link.commands()] == [10.0]
    assert link.ground.drops == {"QUEUE_FULL": 3, "QUEUE_EXPIRED": 7}
    assert link.ground.unsent == 10


def test_the_ground_end_rekeys_before_its_transfer_numbers_wrap(clock: ManualClock) -> None:
    link = connected(clock)
    session = link.ground.session
    beat = plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4))
    first = link.ground.sender.transfer  # where the session began
    link.ground.sender.transfer = first + REKEY_TRANSFERS - 2
    assert len(link.ground.from_local(beat)) == 1
    out = link.ground.from_local(beat)  # the 30,000th transfer: a new handshake goes out
    assert len(out) > 1
    link.ground.sender.transfer = first + TRANSFER_LIMIT  # its HS1 lost meanwhile
    link.ground.from_local(arm())  # no more sending in the old session: queued
    assert link.ground.session is None
    link.up(link.ground.handshake())
    assert link.ground.session is not session and len(link.commands()) == 1


def test_forged_hint_is_ignored_while_telemetry_flows(clock: ManualClock) -> None:
    link = connected(clock)
    link.down(link.vehicle.from_local(plain(lambda m: m.heartbeat_send(2, 3, 0, 0, 4), sysid=1)))
    session = link.ground.session
    assert link.ground.from_air(link.vehicle.hint()[0]).air == []
    assert link.ground.session is session


def test_unknown_local_message_is_refused_before_sealing(clock: ManualClock) -> None:
    link = connected(clock)
    raw = bytearray(plain(lambda m: m.heartbeat_send(6, 8, 0, 0, 4)))
    raw[7:10] = (60999).to_bytes(3, "little")  # a message id nobody knows
    with pytest.raises(InvalidFrameError, match="not in the dialect"):
        link.ground.from_local(bytes(raw))
