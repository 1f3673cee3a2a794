"""The post-quantum carriage through a real MAVProxy: ground station -> ground end -> MAVProxy
-> vehicle end -> a pymavlink vehicle on a serial pseudo-terminal, and back.

MAVProxy (from PyPI, headless, no signing, no dialect of ours) forwards the ``PQ_CHUNK``
messages as unknown messages, untouched.  An attacker sends straight to the vehicle end's
air port what it captured on the air (the ground end's ``tap``).  A second test puts the
vehicle end behind the MAVLink router's trusted endpoint.  Every wait polls an observable
event under a deadline.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from cryptography.hazmat.primitives.asymmetric import mldsa, mlkem

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil

from antireplay.audit import AuditLog
from antireplay.mavlink import Role
from antireplay.mavlink.codec import parse_frame
from antireplay.mavlink.endpoints import open_transport, parse_endpoint
from antireplay.mavlink.pq import (
    DIALECT,
    MSG_CHUNK,
    ChunkKind,
    GroundEnd,
    VehicleEnd,
    pack_v2,
    parse_chunk,
)
from antireplay.mavlink.pq.link import PqLink
from antireplay.pq.session import Initiator, Responder
from antireplay.state.sqlite import SqliteStore
from antireplay.wiring import RouterOptions, build_mavlink_router
from harness import free_port, until
from harness.mavproxy import KEY, PqRig, PtyVehicle
from harness.stores import aged_state

ARM, SERVO = 400, 183


@pytest.fixture
def setup(tmp_path: Path) -> Iterator[PqRig]:
    made = PqRig(tmp_path)
    try:
        yield made
    finally:
        made.close()


def transfers(frames: list[bytes]) -> dict[int, list[bytes]]:
    """The chunk frames grouped by transfer number, in the order they were sent (repair
    requests aside)."""
    grouped: dict[int, list[bytes]] = {}
    for raw in frames:
        if parse_frame(raw).msgid != MSG_CHUNK:
            continue
        chunk = parse_chunk(parse_frame(raw))
        grouped.setdefault(chunk.transfer, []).append(raw)
    return grouped


def command_transfers(frames: list[bytes]) -> list[list[bytes]]:
    return [group for group in transfers(frames).values() if len(group) == 22]  # 2 parity


def retarget(raw: bytes, at: int, value: int) -> bytes:
    """One payload byte rewritten, the MAVLink CRC fixed (a man in the middle would)."""
    frame = parse_frame(raw)
    payload = bytearray(frame.payload.ljust(DIALECT[MSG_CHUNK][1], b"\0"))
    payload[at] = value
    crc_extra = DIALECT[MSG_CHUNK][0]
    return pack_v2(
        MSG_CHUNK, bytes(payload), crc_extra, sysid=frame.sysid, compid=frame.compid, seq=0
    )


def drops(link: PqLink, code: str) -> Callable[[], int]:
    return lambda: link.dropped[f"air:{code}"]


def test_pq_commands_through_mavproxy(setup: PqRig) -> None:
    vehicle = setup.vehicle
    # The handshake went through MAVProxy; wrapped telemetry comes back, unwrapped.
    until("vehicle telemetry at the ground station", setup.heard_vehicle)
    handshakes = [
        group
        for group in transfers(setup.captured).values()
        if parse_chunk(parse_frame(group[0])).kind is ChunkKind.HS1
    ]
    hs1 = handshakes[-1]  # the one that opened the session (MAVProxy may start later)
    assert len(set(hs1)) == 29  # 26 chunks and 3 parity (resent whole if the first was lost)

    # ARM arrives once, as the ground station sent it.
    setup.gcs.mav.command_long_send(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0)
    until("ARM at the vehicle", lambda: vehicle.commands(ARM))
    (arm,) = vehicle.commands(ARM)
    assert arm.get_srcSystem() == 255 and arm.param1 == 1
    until("the ARM transfer captured", lambda: command_transfers(setup.captured))
    (captured_arm,) = command_transfers(setup.captured)

    # Its replay, straight onto the air port: dropped.
    setup.inject(captured_arm)
    until("the replay refused", drops(setup.vehicle_link, "REPLAY_DETECTED"))

    # A man in the middle: the target rewritten, the message id rewritten, two commands
    # spliced into one transfer, the handshake replayed: nothing passes.
    setup.gcs.mav.command_long_send(1, 1, SERVO, 0, 42, 0, 0, 0, 0, 0, 0)
    until("DO_SET_SERVO at the vehicle", lambda: vehicle.commands(SERVO))
    until("both captured", lambda: len(command_transfers(setup.captured)) == 2)
    servo = command_transfers(setup.captured)[1]
    forged_target = [retarget(servo[0], 6 + 10 + 6 + 30, 7), *servo[1:]]
    setup.inject([retarget(raw, 0, 0x77) for raw in forged_target])  # a fresh transfer number
    until("the retargeted chunk refused", drops(setup.vehicle_link, "SIGNATURE_INVALID"))
    header = bytearray(servo[0])
    header[7] = 76  # COMMAND_LONG's id in the outer header: plain MAVLink, never carried
    plain = setup.vehicle_link.dropped["air:PLAIN"]  # MAVProxy's own heartbeats among them
    setup.inject([bytes(header)])
    until(
        "the re-identified chunk dropped",
        lambda: setup.vehicle_link.dropped["air:PLAIN"] > plain,
    )
    splice = [retarget(raw, 0, 0x55) for raw in captured_arm[:10] + servo[10:]]
    before = setup.vehicle_link.dropped["air:SIGNATURE_INVALID"]
    setup.inject(splice)
    until(
        "the spliced chunks refused",
        lambda: setup.vehicle_link.dropped["air:SIGNATURE_INVALID"] >= before + 20,
    )
    sessions = len(setup.responder)
    replays = setup.vehicle_link.dropped["air:REPLAY_DETECTED"]
    setup.inject(hs1)
    until(
        "the handshake replay refused",
        lambda: setup.vehicle_link.dropped["air:REPLAY_DETECTED"] > replays,
    )
    assert len(setup.responder) == sessions

    # The vehicle end restarts: the ground end learns it (PQ_STATUS while the vehicle is
    # silent) and hand-shakes again; the capture from the previous session is dropped.
    ground_end = setup.ground_link.end
    assert isinstance(ground_end, GroundEnd)
    old_session = ground_end.session
    setup.vehicle_link.stop()
    setup.vehicle_link = setup.start_vehicle_end()
    until("a new session after the vehicle end restarted", lambda: len(setup.responder) == 1)
    until("the ground end in it", lambda: ground_end.session is not old_session)
    setup.inject(captured_arm)
    until("the old session's ARM refused", drops(setup.vehicle_link, "UNKNOWN_SESSION"))
    setup.gcs.mav.command_long_send(1, 1, ARM, 0, 0, 0, 0, 0, 0, 0, 0)  # DISARM
    until("DISARM at the vehicle", lambda: len(vehicle.commands(ARM)) == 2)

    # The ground end restarts: a new session at once; the old captures stay dead.
    setup.ground_link.stop()
    setup.ground_link = setup.start_ground_end()
    until("a second session", lambda: len(setup.responder) == 2)
    setup.inject(captured_arm)
    setup.gcs.mav.command_long_send(1, 1, SERVO, 0, 43, 0, 0, 0, 0, 0, 0)
    until("the new ground end's command", lambda: len(vehicle.commands(SERVO)) == 2)
    assert [c.param1 for c in vehicle.commands(ARM)] == [1, 0]
    assert [c.param1 for c in vehicle.commands(SERVO)] == [42, 43]
    assert all(m.get_srcSystem() == 255 for m in vehicle.received)


def test_vehicle_end_behind_the_mavlink_router(tmp_path: Path) -> None:
    """The vehicle end delivers to the router's trusted endpoint, which signs for it with the
    flight controller's MAVLink key: the autopilot verifies every command it gets."""
    vehicle = PtyVehicle()  # signs and verifies with KEY
    trusted, air, local = free_port(), free_port(), free_port()
    store = SqliteStore(aged_state(tmp_path / "mav.db"))  # a deployment started earlier
    audit = AuditLog(tmp_path / "audit.db")
    router = build_mavlink_router(
        [
            (Role.VEHICLE, f"{vehicle.device},57600", KEY),
            (Role.TRUSTED, f"udpin:127.0.0.1:{trusted}", None),
        ],
        store,
        audit,
        RouterOptions(system_id=1),
    )
    router.start()
    gcs_key, kem = mldsa.MLDSA87PrivateKey.generate(), mlkem.MLKEM1024PrivateKey.generate()
    links = [
        PqLink(
            VehicleEnd(Responder(kem, {"gcs": gcs_key.public_key()})),
            open_transport(parse_endpoint(f"udpout:127.0.0.1:{trusted}")),
            open_transport(parse_endpoint(f"udpin:127.0.0.1:{air}")),
        ),
        PqLink(
            GroundEnd(Initiator("gcs", gcs_key), kem.public_key()),
            open_transport(parse_endpoint(f"udpin:127.0.0.1:{local}")),
            open_transport(parse_endpoint(f"udpout:127.0.0.1:{air}")),
        ),
    ]
    for link in links:
        link.start()
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{local}", source_system=255)
    try:
        gcs.mav.command_long_send(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0)  # waits for the session
        until("ARM at the autopilot, signed by the router", lambda: vehicle.commands(ARM))
        (arm,) = vehicle.commands(ARM)
        assert arm.get_signed() and arm.get_link_id() == 251 and arm.get_srcSystem() == 255
        assert vehicle.rejected == 0
    finally:
        gcs.close()
        for link in links:
            link.stop()
        router.stop()
        audit.close()
        store.close()
        vehicle.close()
