"""Sealed vs plain DDS topics on loopback (Cyclone DDS): samples per second and latency.

Run: ``python -m benchmarks.bench_dds``.  Baseline: a plain topic of the same wire
type carrying the payload unsealed, in the same process and domain.  Rounds of the
two alternate (interleaved) and the medians are compared.  Throughput: write a
batch, take until all arrived.  Latency: one sample at a time, write to hand-over.
Both sides run in one process, so Cyclone delivers locally (no UDP hop): the ratio is
the worst case, a network adds the same cost to both.  The sealed reader keeps its
epochs in the default memory store (a ``sqlite:`` store adds one store write per
accepted sample; see bench_epochs).

Time to first accept: a reader on the memory store refuses everything sealed before it
started plus ``max_forward_s`` (its restart fence) unless a writer answers its challenge.
A writer on another participant writes every ``PERIOD_S``; a new reader polls until it
accepts, with challenges off (the fence) and on, at ``max_forward_s`` 5 and 60 (the fence
at 60 takes a minute of real time).
"""

from __future__ import annotations

import os
import random
import statistics
import threading
import time
from collections.abc import Callable

from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from antireplay.dds.domain import join_domain
from antireplay.dds.topics import SealedReader, SealedWriter, default_qos
from antireplay.dds.wire import SealedSample

PSK = os.urandom(32)
PAYLOAD = b"cmd_vel linear=0.50 angular=0.10 frame=base_link " * 2
BATCH, SINGLES, ROUNDS = 2_000, 200, 5
PERIOD_S = 0.1


class Plain:
    """The baseline: the same wire type, no seal, no verification."""

    def __init__(self, participant: DomainParticipant) -> None:
        qos = default_qos(BATCH)
        topic = Topic(participant, "bench/plain", SealedSample, qos=qos)
        self.writer = DataWriter(participant, topic, qos=qos)
        self.reader = DataReader(participant, topic, qos=qos)

    def send(self) -> None:
        self.writer.write(SealedSample(instance="arm", sealed=PAYLOAD))

    def receive(self) -> int:
        return sum(len(bytes(s.sealed)) > 0 for s in self.reader.take(N=BATCH))


class Sealed:
    def __init__(self, participant: DomainParticipant) -> None:
        qos = default_qos(BATCH)
        self.reader = SealedReader(participant, "bench/sealed", PSK, qos=qos)
        self.writer = SealedWriter(participant, "bench/sealed", PSK, qos=qos)

    def send(self) -> None:
        self.writer.write(PAYLOAD, instance="arm")

    def receive(self) -> int:
        verdicts = self.reader.take(BATCH)
        assert all(v.accepted for v in verdicts)
        return len(verdicts)


def _drain_until(receive: Callable[[], int], count: int) -> None:
    got, deadline = 0, time.monotonic() + 30
    while got < count:
        got += receive()
        if time.monotonic() > deadline:
            raise RuntimeError(f"only {got} of {count} samples arrived")


def throughput(side: Plain | Sealed) -> float:
    """Samples per second, written and taken in one batch."""
    start = time.perf_counter()
    for _ in range(BATCH):
        side.send()
    _drain_until(side.receive, BATCH)
    return BATCH / (time.perf_counter() - start)


def latency_us(side: Plain | Sealed) -> float:
    """Median microseconds from write to hand-over, one sample in flight."""
    samples = []
    for _ in range(SINGLES):
        start = time.perf_counter()
        side.send()
        _drain_until(side.receive, 1)
        samples.append((time.perf_counter() - start) * 1e6)
    return statistics.median(samples)


def time_to_first_accept(domain_id: int, *, challenge: bool, forward_s: float) -> float:
    """Seconds from a new reader's construction to its first accepted sample."""
    writer = SealedWriter(join_domain(domain_id), "bench/fresh", PSK, max_forward_s=forward_s)
    stop = threading.Event()

    def write() -> None:
        while not stop.wait(PERIOD_S):
            writer.write(PAYLOAD, instance="arm")

    thread = threading.Thread(target=write, daemon=True)
    thread.start()
    try:
        time.sleep(0.5)  # the writer has been running: its earlier samples are captures
        start = time.perf_counter()
        reader = SealedReader(join_domain(domain_id), "bench/fresh", PSK,
                              max_forward_s=forward_s, challenge=challenge)  # fmt: skip
        while not any(v.accepted for v in reader.poll(0.05)):
            if time.perf_counter() - start > forward_s + 30:
                raise RuntimeError("no sample accepted")
        return time.perf_counter() - start
    finally:
        stop.set()
        thread.join()


def warm_up(side: Sealed) -> None:
    """Until the new reader accepts (its challenge answered by the first writes)."""
    while not any(v.accepted for v in side.reader.poll(0.01)):
        side.writer.write(PAYLOAD, instance="arm")
    while side.reader.poll(0.2):
        pass


def main() -> None:
    domain_id = random.randrange(150, 225)
    for forward_s in (5.0, 60.0):
        fence, asked = (
            time_to_first_accept(domain_id + i, challenge=c, forward_s=forward_s)
            for i, c in ((1, False), (2, True))
        )
        print(f"time to first accept, max_forward_s={forward_s:>4.0f}: "
              f"fence {fence:6.3f} s   challenge {asked:6.3f} s")  # fmt: skip
    participant = join_domain(domain_id)
    sealed = Sealed(participant)
    warm_up(sealed)
    sides: dict[str, Plain | Sealed] = {"plain": Plain(participant), "sealed": sealed}
    rates: dict[str, list[float]] = {name: [] for name in sides}
    lat: dict[str, list[float]] = {name: [] for name in sides}
    for _ in range(ROUNDS):
        for name, side in sides.items():
            rates[name].append(throughput(side))
            lat[name].append(latency_us(side))
    rate = {name: statistics.median(v) for name, v in rates.items()}
    us = {name: statistics.median(v) for name, v in lat.items()}
    for name in sides:
        print(f"{name:<7} topic {rate[name]:>10,.0f} samples/s   latency {us[name]:>7.0f} us")
    print(
        f"sealed/plain: throughput {rate['sealed'] / rate['plain']:.2f}x, "
        f"latency +{us['sealed'] - us['plain']:.0f} us ({us['sealed'] / us['plain']:.2f}x)"
    )


if __name__ == "__main__":
    main()
