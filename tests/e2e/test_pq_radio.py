"""The radio the PQ benchmark runs through (:mod:`harness.radio`), and the benchmark
itself (``python -m benchmarks pq-radio``) on a tiny run: the figures it prints come from a
relay that loses what it says, paces what it says, and a benchmark that runs end to end."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest

from harness import ROOT, until
from harness.radio import Radio, airtime


class Ends:
    """The ground side and the vehicle side of a radio: two plain UDP sockets."""

    def __init__(self) -> None:
        self.vehicle = self._socket()
        self.ground = self._socket()
        self.vehicle_address = self.vehicle.getsockname()

    @staticmethod
    def _socket() -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        sock.bind(("127.0.0.1", 0))
        sock.settimeout(10)
        return sock

    def drain(self, sock: socket.socket) -> list[bytes]:
        """Everything waiting on ``sock`` now."""
        got: list[bytes] = []
        sock.setblocking(False)
        try:
            while True:
                got.append(sock.recv(65_536))
        except BlockingIOError:
            return got
        finally:
            sock.settimeout(10)

    def close(self) -> None:
        self.vehicle.close()
        self.ground.close()


@pytest.fixture
def ends() -> Iterator[Ends]:
    made = Ends()
    try:
        yield made
    finally:
        made.close()


def send_one_by_one(radio: Radio, ends: Ends, count: int) -> None:
    """``count`` numbered datagrams, each taken by the radio before the next is sent (no
    socket buffer can drop one, and the RNG sees them in order)."""
    for i in range(count):
        ends.ground.sendto(i.to_bytes(4, "big"), ("127.0.0.1", radio.port))
        until("the radio took it", lambda: radio.counts()["uplink"].received > i)  # noqa: B023


def test_the_radio_carries_both_ways_and_counts_bytes(ends: Ends) -> None:
    with Radio(ends.vehicle_address) as radio:
        ends.ground.sendto(b"x" * 100, ("127.0.0.1", radio.port))
        data, air_side = ends.vehicle.recvfrom(65_536)
        assert data == b"x" * 100
        ends.vehicle.sendto(b"y" * 30, air_side)  # the answer goes to the learned ground peer
        assert ends.ground.recv(65_536) == b"y" * 30
        counts = radio.counts()
    assert (counts["uplink"].on_air_bytes, counts["uplink"].delivered) == (100, 1)
    assert (counts["downlink"].on_air_bytes, counts["downlink"].delivered) == (30, 1)
    assert radio.on_air_bytes() == 130


def test_loss_is_per_datagram_and_seeded(ends: Ends) -> None:
    def delivered(seed: int) -> set[int]:
        with Radio(ends.vehicle_address, loss=0.3, seed=seed) as radio:
            send_one_by_one(radio, ends, 200)
            counts = radio.counts()["uplink"]
        got = {int.from_bytes(d, "big") for d in ends.drain(ends.vehicle)}
        assert counts.lost + counts.delivered == counts.on_air == 200
        assert len(got) == counts.delivered
        return got

    first, again, other = delivered(7), delivered(7), delivered(8)
    assert first == again  # the same seed loses the same datagrams
    assert first != other
    assert 120 <= len(first) <= 160  # 30 % lost of 200: 140 expected, independently drawn
    with Radio(ends.vehicle_address, loss=1.0) as radio:
        send_one_by_one(radio, ends, 5)
    assert radio.counts()["uplink"].lost == 5 and ends.drain(ends.vehicle) == []


def test_a_limited_link_spends_each_datagram_s_airtime(ends: Ends) -> None:
    """At 57,600 baud five 288-byte datagrams take 5 x 50 ms: the last cannot arrive sooner
    (a lower bound: the radio can be late, never early)."""
    with Radio(ends.vehicle_address, bps=57_600) as radio:
        for _ in range(5):
            ends.ground.sendto(b"z" * 288, ("127.0.0.1", radio.port))
        for _ in range(5):
            ends.vehicle.recv(65_536)
        last = time.monotonic()
        first = radio.counts()["uplink"].first_at
    assert first is not None
    assert last - first >= 5 * airtime(288, 57_600) == pytest.approx(0.25)


def test_a_full_queue_drops_what_arrives(ends: Ends) -> None:
    """At 800 baud one 576-byte datagram is 7.2 s on air: a burst of ten finds a 2,048-byte
    queue holding three, and the other seven are dropped as they arrive."""
    with Radio(ends.vehicle_address, bps=800, queue_bytes=2_048) as radio:
        for _ in range(10):
            ends.ground.sendto(b"q" * 576, ("127.0.0.1", radio.port))
        until("the burst taken", lambda: radio.counts()["uplink"].received == 10)
        counts = radio.counts()["uplink"]
    assert (counts.overflowed, counts.on_air, counts.lost) == (7, 0, 0)


def test_the_radio_runs_as_a_process(ends: Ends) -> None:
    host, port = ends.vehicle_address
    proc = subprocess.Popen(
        [sys.executable, "-m", "harness.radio", "--remote", f"{host}:{port}", "--seed", "3"],
        cwd=ROOT, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        radio_port = int(proc.stdout.readline().split()[1])
        ends.ground.sendto(b"hello", ("127.0.0.1", radio_port))
        assert ends.vehicle.recv(65_536) == b"hello"
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0
    counts = json.loads(out.strip().splitlines()[-1])
    assert counts["uplink"]["delivered_bytes"] == 5 and counts["downlink"]["received"] == 0


def benchmarks(*args: str) -> subprocess.CompletedProcess[str]:
    """``python -m benchmarks ARGS`` from the checkout, as a user runs it."""
    return subprocess.run(
        [sys.executable, "-m", "benchmarks", *args],
        check=False, cwd=ROOT, capture_output=True, text=True, timeout=240,
    )  # fmt: skip


def test_benchmark_names_and_options() -> None:
    """``pq-radio`` and ``pq_radio`` name one benchmark; options go to exactly one."""
    for name in ("pq-radio", "pq_radio", "bench_pq_radio"):
        run = benchmarks(name, "--help")
        assert run.returncode == 0 and "python -m benchmarks pq-radio" in run.stdout, run
    refused = benchmarks("window", "pq-radio", "--commands", "3")
    assert refused.returncode == 1 and "exactly one" in refused.stderr, refused


def test_the_benchmark_runs_a_tiny_configuration() -> None:
    """Three commands at 0 % loss, unlimited: every one delivered on both paths, none
    executed twice, a session, the table printed."""
    run = benchmarks("pq-radio", "--commands", "3", "--loss", "0", "--bps", "0")
    assert run.returncode == 0, run.stdout + run.stderr
    out = run.stdout
    (row,) = [line for line in out.splitlines() if line.startswith("| unlimited")]
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    assert cells[3] == "3/3" and cells[7] == "3/3", row  # PQ and signed MAVLink
    assert cells[6].endswith(" s"), row  # the session came up
    assert int(cells[5].replace(",", "")) > 4_000 > int(cells[9].replace(",", "")), row
    assert cells[10] == "0/0", row
    assert "replayed transmissions executed: 0" in out
    assert "| link | loss | seed | PQ delivered |" in out
