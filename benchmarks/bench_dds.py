"""Sealed vs plain DDS topics on loopback (Cyclone DDS): samples per second and latency.

Run: ``python -m benchmarks.bench_dds``.  Baseline: a plain topic of the same wire
type carrying the payload unsealed, in the same process and domain.  Rounds of the
two alternate (interleaved) and the medians are compared.  Throughput: write a
batch, take until all arrived.  Latency: one sample at a time, write to hand-over.
Both sides run in one process, so Cyclone delivers locally (no UDP hop): the ratio is
the worst case, a network adds the same cost to both.  The sealed reader keeps its
epochs in the default memory store (a ``sqlite:`` store adds one store write per
accepted sample; see bench_epochs).  A reader on the memory store refuses everything
sealed before it started plus ``max_forward_s`` (its restart fence), so the benchmark
waits that long after creating the reader, as a deployment does after each start.
"""

from __future__ import annotations

import os
import random
import statistics
import time
from collections.abc import Callable

from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from antireplay.dds.config import MAX_FORWARD_S
from antireplay.dds.domain import join_domain
from antireplay.dds.topics import SealedReader, SealedWriter, default_qos
from antireplay.dds.wire import SealedSample

PSK = os.urandom(32)
PAYLOAD = b"cmd_vel linear=0.50 angular=0.10 frame=base_link " * 2
BATCH, SINGLES, ROUNDS = 2_000, 200, 5


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


def main() -> None:
    participant = join_domain(random.randrange(150, 230))
    sides: dict[str, Plain | Sealed] = {"plain": Plain(participant), "sealed": Sealed(participant)}
    time.sleep(MAX_FORWARD_S + 0.1)  # the memory store's start fence (module docstring)
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
