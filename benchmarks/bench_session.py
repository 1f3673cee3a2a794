"""The post-quantum MAVLink carriage: bytes on air, commands per second, added latency.

Run: ``python -m benchmarks.bench_session``.

1. **Bytes on air** (exact, computed from the frames the ends produce): one
   COMMAND_LONG as plain MAVLink v2, MAVLink-signed, in our carriage (ML-DSA-87 command
   frame, 20 chunks and 2 parity) and in CleitonQ's draft format (20 ``CLEITONQ_CHUNK`` frames of
   245 data bytes; counted as full 255-byte payloads, the draft's framing); the
   handshake; one second of a typical 57,600-baud telemetry stream (HEARTBEAT 1 Hz,
   SYS_STATUS 1 Hz, ATTITUDE 10 Hz, GLOBAL_POSITION_INT 5 Hz, VFR_HUD 2 Hz) plain,
   MAVLink-signed and in our carriage (HMAC session frames).  Airtime at 57,600 baud
   (8N1: 5,760 bytes per second).
2. **Commands per second and added latency** on the same in-process path (no I/O):
   ground end wraps a COMMAND_LONG, vehicle end reassembles, verifies and unwraps it;
   beside classic MAVLink signing: the router signs (``sign_frame``) and the guard
   verifies (``MavlinkGuard.open``).  Median microseconds per command (the latency the
   ends add, radio airtime aside) and commands per second.
3. **End to end on loopback UDP** (threads in this process, real sockets): a ground station
   sends ``LATENCY_N`` COMMAND_LONGs one at a time to the ground end, which carries them to
   the vehicle end, which delivers them to a flight-controller socket; beside the MAVLink
   router (SQLite store) signing the same commands on behalf of a trusted endpoint and
   forwarding them to the same socket.  Median and p90 milliseconds from send to receipt.
"""

from __future__ import annotations

import os
import socket
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric import mldsa, mlkem
from pymavlink.dialects.v20 import ardupilotmega as dialect

from antireplay import ManualClock
from antireplay.audit import AuditLog
from antireplay.mavlink import MavlinkGuard, Role, TimestampSource, passphrase_key, sign_frame
from antireplay.mavlink.endpoints import open_transport, parse_endpoint
from antireplay.mavlink.pq import GroundEnd, VehicleEnd
from antireplay.mavlink.pq.link import PqLink
from antireplay.pq.session import Initiator, Responder
from antireplay.state.sqlite import SqliteStore
from antireplay.wiring import RouterOptions, build_mavlink_router
from benchmarks._timing import per_op_ns, rate
from harness import free_port

os.environ["MAVLINK20"] = "1"
BAUD_BYTES_S = 57_600 / 10
LATENCY_N = 50
CLEITONQ_CHUNKS, CLEITONQ_FRAME = 20, 12 + 255
#: (name, Hz, builder) of a typical telemetry stream on a 57,600-baud radio.
STREAM: tuple[tuple[str, int, Callable[[dialect.MAVLink], None]], ...] = (
    ("HEARTBEAT", 1, lambda m: m.heartbeat_send(2, 3, 0, 0, 4)),
    ("SYS_STATUS", 1, lambda m: m.sys_status_send(1, 1, 1, 500, 12000, 100, 80, 0, 0, 0, 0, 0, 0)),
    ("ATTITUDE", 10, lambda m: m.attitude_send(1, 0.1, 0.2, 0.3, 0.01, 0.02, 0.03)),
    ("GLOBAL_POSITION_INT", 5, lambda m: m.global_position_int_send(1, 1, 2, 3, 4, 5, 6, 7, 8)),
    ("VFR_HUD", 2, lambda m: m.vfr_hud_send(12.0, 11.0, 90, 50, 30.0, 0.5)),
)


class _Sink:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.frames.append(bytes(data))


def _mav(sysid: int, key: bytes | None = None) -> tuple[dialect.MAVLink, _Sink]:
    sink = _Sink()
    mav = dialect.MAVLink(sink, srcSystem=sysid, srcComponent=190 if sysid == 255 else 1)
    if key is not None:
        mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.link_id = key, True, 1
        mav.signing.timestamp = 1
    return mav, sink


def _connected(clock: ManualClock) -> tuple[GroundEnd, VehicleEnd, int]:
    """Both ends with a session; returns the handshake's bytes on air."""
    gcs_key, kem = mldsa.MLDSA87PrivateKey.generate(), mlkem.MLKEM1024PrivateKey.generate()
    ground = GroundEnd(Initiator("gcs", gcs_key, clock), kem.public_key(), clock=clock)
    vehicle = VehicleEnd(Responder(kem, {"gcs": gcs_key.public_key()}, clock=clock), clock=clock)
    air = 0
    for raw in ground.handshake():
        air += len(raw)
        for back in vehicle.from_air(raw).air:
            air += len(back)
            ground.from_air(back)
    return ground, vehicle, air


def bytes_on_air() -> None:
    clock = ManualClock()
    ground, vehicle, handshake = _connected(clock)
    mav, sink = _mav(255)
    mav.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    plain = sink.frames[-1]
    smav, ssink = _mav(255, passphrase_key("x"))
    smav.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    chunks = ground.from_local(plain)
    ours = sum(map(len, chunks))
    cleitonq = CLEITONQ_CHUNKS * CLEITONQ_FRAME
    print("One COMMAND_LONG (ARM) on air:")
    rows = [
        ("plain MAVLink v2", 1, len(plain)),
        ("MAVLink v2 signed", 1, len(ssink.frames[-1])),
        ("ours (ML-DSA-87 command frame)", len(chunks), ours),
        ("CleitonQ draft (CLEITONQ_CHUNK)", CLEITONQ_CHUNKS, cleitonq),
    ]
    for name, frames, size in rows:
        airtime = size / BAUD_BYTES_S * 1000
        print(f"  {name:34} {frames:>3} frames {size:>6,} B  {airtime:>7.1f} ms at 57,600 baud")
    print(f"  handshake (HS1 + HS2): {handshake:,} B, {handshake / BAUD_BYTES_S:.2f} s")
    per_s = {"plain": 0, "signed": 0, "ours": 0}
    fc, fc_sink = _mav(1)
    sfc, sfc_sink = _mav(1, passphrase_key("x"))
    for _name, hz, build in STREAM:
        build(fc)
        build(sfc)
        wrapped = vehicle.from_local(fc_sink.frames[-1])
        per_s["plain"] += hz * len(fc_sink.frames[-1])
        per_s["signed"] += hz * len(sfc_sink.frames[-1])
        per_s["ours"] += hz * sum(map(len, wrapped))
    print("One second of telemetry (19 messages):")
    for name, size in per_s.items():
        print(f"  {name:8} {size:>6,} B/s  {size / BAUD_BYTES_S:>6.1%} of the radio")


def commands_per_second() -> None:
    clock = ManualClock()
    ground, vehicle, _ = _connected(clock)
    mav, sink = _mav(255)
    mav.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    plain = sink.frames[-1]

    def pq_command() -> None:
        for raw in ground.from_local(plain):
            out = vehicle.from_air(raw)
        assert out.local

    key = passphrase_key("bench")
    guard = MavlinkGuard(key, clock=clock, system_id=1)
    stamps = TimestampSource(clock)

    def signed_command() -> None:
        guard.open(sign_frame(plain, key, 1, stamps))

    pq = per_op_ns(pq_command, 200)
    classic = per_op_ns(signed_command, 2_000)
    print("Per command, wrap + carry + verify + unwrap, in process (radio airtime aside):")
    print(f"  ours (ML-DSA-87, 20+2 chunks) {pq / 1000:>8.1f} us {rate(pq)}")
    print(f"  MAVLink signing (HMAC, 1 frame) {classic / 1000:>6.1f} us {rate(classic)}")
    print(f"  ratio {pq / classic:.0f}x")


def _latencies(send: Callable[[int], None], fc: socket.socket) -> list[float]:
    """Milliseconds from ``send(i)`` to a COMMAND_LONG with ``param1 == i`` at ``fc``."""
    decoder, out = dialect.MAVLink(_Sink()), []
    for i in range(LATENCY_N):
        start = time.perf_counter()
        send(i)
        while True:
            data = fc.recv(65_535)
            msgs = [m for m in decoder.parse_buffer(data) or [] if m.get_type() == "COMMAND_LONG"]
            if any(m.param1 == i for m in msgs):
                break
        out.append((time.perf_counter() - start) * 1000)
    return out


def _fc_socket() -> socket.socket:
    fc = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    fc.bind(("127.0.0.1", 0))
    fc.settimeout(10)
    return fc


def _pq_path(fc: socket.socket) -> list[float]:
    gcs_key, kem = mldsa.MLDSA87PrivateKey.generate(), mlkem.MLKEM1024PrivateKey.generate()
    air, local = free_port(), free_port()
    fc_port = fc.getsockname()[1]
    vehicle = PqLink(
        VehicleEnd(Responder(kem, {"gcs": gcs_key.public_key()})),
        open_transport(parse_endpoint(f"udpout:127.0.0.1:{fc_port}")),
        open_transport(parse_endpoint(f"udpin:127.0.0.1:{air}")),
    )
    ground_end = GroundEnd(Initiator("gcs", gcs_key), kem.public_key())
    ground = PqLink(
        ground_end,
        open_transport(parse_endpoint(f"udpin:127.0.0.1:{local}")),
        open_transport(parse_endpoint(f"udpout:127.0.0.1:{air}")),
    )
    vehicle.start()
    ground.start()
    gcs = dialect.MAVLink(_Udp(("127.0.0.1", local)), srcSystem=255, srcComponent=190)
    try:
        while ground_end.session is None:
            time.sleep(0.01)
        return _latencies(lambda i: gcs.command_long_send(1, 1, 400, 0, i, 0, 0, 0, 0, 0, 0), fc)
    finally:
        ground.stop()
        vehicle.stop()


def _router_path(fc: socket.socket) -> list[float]:
    trusted, fc_port = free_port(), fc.getsockname()[1]
    with tempfile.TemporaryDirectory() as tmp:
        # A deployment started 10 min ago: a new state fences the router's first start.
        SqliteStore(Path(tmp) / "mav.db", clock=ManualClock(wall=time.time() - 600)).close()
        store, audit = SqliteStore(Path(tmp) / "mav.db"), AuditLog(Path(tmp) / "audit.db")
        key = passphrase_key("bench")
        router = build_mavlink_router(
            [
                (Role.VEHICLE, f"udpout:127.0.0.1:{fc_port}", key),
                (Role.TRUSTED, f"udpin:127.0.0.1:{trusted}", None),
            ],
            store,
            audit,
            RouterOptions(system_id=1),
        )
        router.start()
        tool = dialect.MAVLink(_Udp(("127.0.0.1", trusted)), srcSystem=200, srcComponent=1)
        try:
            return _latencies(
                lambda i: tool.command_long_send(1, 1, 400, 0, i, 0, 0, 0, 0, 0, 0), fc
            )
        finally:
            router.stop()
            audit.close()
            store.close()


def end_to_end() -> None:
    print(f"End to end on loopback UDP, {LATENCY_N} commands one at a time (ms, p50 / p90):")
    for name, path in (("ours, two ends", _pq_path), ("MAVLink router", _router_path)):
        fc = _fc_socket()
        try:
            samples = sorted(path(fc))
        finally:
            fc.close()
        p50, p90 = statistics.median(samples), samples[int(len(samples) * 0.9)]
        print(f"  {name:16} {p50:>7.2f} / {p90:>7.2f}")


class _Udp:
    def __init__(self, to: tuple[str, int]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.to = to

    def write(self, data: bytes) -> None:
        self.sock.sendto(data, self.to)


def main() -> None:
    bytes_on_air()
    commands_per_second()
    end_to_end()


if __name__ == "__main__":
    main()
