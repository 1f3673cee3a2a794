"""The router in a real setup: MAVProxy (from PyPI) as the ground station, signing by
passphrase; a pymavlink vehicle on a serial pseudo-terminal; a tool that cannot sign on a
trusted UDP endpoint; an attacker on the untrusted link.

MAVProxy takes its key from ``$HOME/.mavproxy/signing.keys`` (``ENDPOINT PASSPHRASE``),
as its users set it up, and forwards what an operator sends to its ``--out`` port, signed
(``mavfwd_signing``).  Every wait polls an observable event under a deadline.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

os.environ["MAVLINK20"] = "1"  # pymavlink's mavutil speaks MAVLink 1 unless told otherwise
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay.core.clock import SystemClock
from antireplay.mavlink import mav_time
from harness import until
from harness.mavproxy import TOOL_SYSTEM, RouterRig

ARM = 400  # MAV_CMD_COMPONENT_ARM_DISARM


@pytest.fixture
def setup(tmp_path: Path) -> Iterator[RouterRig]:
    made = RouterRig(tmp_path)
    try:
        yield made
    finally:
        made.close()


def test_mavproxy_ground_station_pty_vehicle_and_an_unsigning_tool(setup: RouterRig) -> None:
    vehicle, router = setup.vehicle, setup.router
    # Telemetry reaches every ground station once it has authenticated.
    until("vehicle telemetry at the operator behind MAVProxy", setup.heard(setup.operator, 1))
    setup.tool.mav.heartbeat_send(18, 8, 0, 0, 0)  # unsigned; the router signs it
    until("vehicle telemetry at the trusted tool", setup.heard(setup.tool, 1))

    # ARM from the operator, signed by MAVProxy with the passphrase's key, arrives once.
    setup.operator.mav.command_long_send(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0)
    until("ARM at the vehicle", lambda: vehicle.commands(ARM))
    arm = vehicle.commands(ARM)[0]
    assert arm.get_signed() and arm.get_srcSystem() == 255
    captured = bytes(arm.get_msgbuf())

    # Its replay from the untrusted link is dropped, and counted with its reason.
    setup.inject(captured)
    until("the replay refused", lambda: router.stats.dropped["inbound:COUNTER_REPLAYED"])

    # The tool's unsigned command reaches the vehicle signed, and pymavlink verifies it.
    setup.tool.mav.command_long_send(1, 1, 183, 0, 42, 0, 0, 0, 0, 0, 0)  # DO_SET_SERVO
    until("the tool's command at the vehicle", lambda: vehicle.commands(183))
    (servo,) = vehicle.commands(183)
    assert servo.get_signed() and servo.get_link_id() == 251
    assert servo.get_srcSystem() == TOOL_SYSTEM and servo.param1 == 42
    assert len(vehicle.commands(ARM)) == 1  # ARM arrived once

    # Frames injected on the untrusted link learn no route (forged, and unsigned).
    forger = dialect.MAVLink(_Keep(), srcSystem=77, srcComponent=1)
    forger.signing.secret_key, forger.signing.sign_outgoing = bytes(32), True
    forger.signing.timestamp = mav_time(SystemClock())
    forger.heartbeat_send(6, 8, 0, 0, 0)
    plain = dialect.MAVLink(_Keep(), srcSystem=78, srcComponent=1)
    plain.heartbeat_send(6, 8, 0, 0, 0)
    injected = [forger.file.frames[-1], plain.file.frames[-1]]
    for raw in injected:
        setup.inject(raw)
    until("both injected frames refused", lambda: len(setup.refusals_of(injected)) == 2)
    refused = [r.code for r in setup.refusals_of(injected)]
    assert refused == ["SIGNATURE_INVALID", "SIGNATURE_REQUIRED"]
    systems = {system for system, _ in router.routes()}
    assert {1, 255, TOOL_SYSTEM} <= systems and not {77, 78} & systems
    assert not any(m.get_srcSystem() in {77, 78} for m in vehicle.received)

    # Restart the router; replay every capture: all dropped.  The honest tool goes on.
    captures = [bytes(m.get_msgbuf()) for m in list(vehicle.received)]
    assert len(captures) >= 3
    setup.stop_router()
    setup.router = router = setup.start_router()
    for raw in captures:
        setup.inject(raw)
    until("every capture refused", lambda: len(setup.refusals_of(captures)) == len(captures))
    codes = {refusal.code for refusal in setup.refusals_of(captures)}
    assert codes <= {"MESSAGE_STALE", "COUNTER_REPLAYED", "WRONG_DIRECTION"}, codes
    seen = len(vehicle.received)
    setup.tool.mav.command_long_send(1, 1, 183, 0, 43, 0, 0, 0, 0, 0, 0)
    until("the tool's command after the restart", lambda: len(vehicle.commands(183)) == 2)
    assert vehicle.commands(183)[1].param1 == 43
    assert not {bytes(m.get_msgbuf()) for m in vehicle.received[len(captures) :]} & set(captures)
    assert vehicle.rejected == 0  # the vehicle's own check never had to refuse anything
    assert len(vehicle.received) > seen


class _Keep:
    """pymavlink's output file, kept in a list."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))
