"""The challenge channel (``antireplay/ping``): challenges and answers authenticated on arrival.

Theory of operation
-------------------
A fenced reader asks writers for a fresh epoch with a CHALLENGE and a writer replies with an
ANSWER (:mod:`antireplay.epochs.policy`), both on :data:`PING_TOPIC`.  Anyone on the domain
can write that topic, so a keyless flood must never push a genuine exchange out (review
finding: a 64-sample history lost every challenge to two junk writers).  Three things make
it so:

* **Authenticated before any space.**  The reader's topic carries a Cyclone topic filter,
  run as a sample arrives and before it takes history, instance or queue space: only a
  frame of the wanted kind, on its own sender's instance, that the owner's ``admit`` finds
  fresh (a read of a nonce snapshot or the clock, nothing written) and whose tag verifies
  under the topic's :class:`~antireplay.epochs.policy.KeyRing` is kept.  The rest is
  counted (``ping_dropped_malformed`` / ``_stale`` / ``_forged``; ``ping_ignored`` for the
  other half of the exchange and other topics) and dropped.
* **One slot set per authenticated sender.**  The instance is ``topic#prefix`` (the
  challenger's, or the answering writer's), keep-last ``OUTSTANDING`` per instance: only
  fleet members get an instance, and one cannot evict another's.
* **QoS**: reliable (a lost exchange costs a retry period), volatile (an old exchange is
  worth nothing to a new peer).

The filter runs on Cyclone's receive thread and takes the GIL while Cyclone holds the
reader's cache lock; the binding's own take and write keep the GIL while they wait for that
lock, a deadlock.  So this channel takes and writes through ``ddsc`` with ctypes, which
lets the GIL go (:func:`_take`, :func:`_write`).  A reader past its fence leaves with
:meth:`PingChannel.close`; filter callbacks stay pinned (:data:`_FILTERS`).
"""

from __future__ import annotations

import ctypes as ct
import threading
from collections import Counter
from collections.abc import Callable

from cyclonedds.core import DDSException, InstanceState, ReadCondition, SampleState, ViewState
from cyclonedds.domain import DomainParticipant
from cyclonedds.internal import dds_c_t, load_cyclonedds
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Sample, Topic
from cyclonedds.util import duration

from antireplay.core.errors import InvalidFrameError
from antireplay.dds.wire import SealedSample
from antireplay.epochs.policy import OUTSTANDING, Claim, KeyRing, Kind, parse
from antireplay.epochs.sealing import claim

#: The control topic of freshness challenges and answers.
PING_TOPIC = "antireplay/ping"
#: Ping samples one call takes at most (the rest wait in the reader's history).
PINGS_PER_CALL = 64

#: Every topic filter's ctypes callback, held for the life of the process: Cyclone keeps
#: calling a filter as long as its C topic lives, and the binding ties the callback to the
#: Python ``Topic`` object, which the garbage collector may free first (a freed callback
#: crashed ``dds_write`` in ``content_filter_accepts``).  One small entry per channel.
_FILTERS: list[object] = []

_ddsc = load_cyclonedds()
_ddsc.dds_take.argtypes = [ct.c_int32, ct.POINTER(ct.c_void_p),
                           ct.POINTER(dds_c_t.sample_info), ct.c_size_t, ct.c_uint32]  # fmt: skip
_ddsc.dds_take.restype = ct.c_int32
_ddsc.dds_return_loan.argtypes = [ct.c_int32, ct.POINTER(ct.c_void_p), ct.c_int32]
_ddsc.dds_return_loan.restype = ct.c_int32
_ddsc.dds_write.argtypes = [ct.c_int32, ct.c_void_p]
_ddsc.dds_write.restype = ct.c_int32


def _take(reader: DataReader[SealedSample], limit: int) -> list[SealedSample]:
    """Take up to ``limit`` samples, the GIL released while Cyclone locks its cache."""
    buffer, infos = (ct.c_void_p * limit)(), (dds_c_t.sample_info * limit)()
    taken = _ddsc.dds_take(reader._ref, buffer, infos, limit, limit)
    if taken < 0:
        raise DDSException(taken, "taking challenge samples")
    samples: list[SealedSample] = []
    try:
        for i in range(taken):
            address = buffer[i]
            if infos[i].valid_data and address:
                held = Sample.from_address(address)
                data = ct.string_at(held.usample, held.usample_size)
                samples.append(SealedSample.deserialize(data))
    finally:
        if taken:
            _ddsc.dds_return_loan(reader._ref, buffer, taken)
    return samples


def _write(writer: DataWriter[SealedSample], sample: SealedSample) -> None:
    """Write one sample, the GIL released (a local reader's filter may need it)."""
    data = sample.serialize()
    data = data.ljust((len(data) + 3) & ~3, b"\0")  # as the binding pads it
    raw = ct.create_string_buffer(data, len(data))
    held = Sample(ct.cast(raw, ct.c_void_p), len(data))
    status = _ddsc.dds_write(writer._ref, ct.byref(held))
    if status < 0:
        raise DDSException(status, "writing a challenge sample")


def ping_qos() -> Qos:
    """Reliable, volatile, keep-last ``OUTSTANDING`` per sender instance (module docstring)."""
    return Qos(
        Policy.Reliability.Reliable(duration(seconds=1)),
        Policy.Durability.Volatile,
        Policy.History.KeepLast(OUTSTANDING),
    )


def ping_instance(topic: str, prefix: bytes) -> str:
    """The instance of a challenge or answer: the topic asked about and its sender's prefix."""
    return f"{topic}#{prefix.hex()}"


class PingChannel:
    """A writer and a filtered reader on :data:`PING_TOPIC` for one sealed topic's endpoint
    (``ring=None``: no filter, a test's rogue)."""

    def __init__(
        self,
        participant: DomainParticipant,
        topic: str,
        ring: KeyRing | None = None,
        *,
        wanted: Kind = Kind.ANSWER,
        admit: Callable[[Claim], bool] | None = None,
        counts: Counter[str] | None = None,
    ) -> None:
        qos = ping_qos()
        self.topic, self.ring, self.wanted, self.admit = topic, ring, wanted, admit
        self.counts: Counter[str] = Counter() if counts is None else counts
        self._head = topic + "#"
        self._count_lock = threading.Lock()
        self.writer = DataWriter(
            participant, Topic(participant, PING_TOPIC, SealedSample, qos=qos), qos=qos
        )
        inbound = Topic(participant, PING_TOPIC, SealedSample, qos=qos)
        if ring is not None:
            inbound.set_topic_filter(lambda _topic, sample: self._keep(sample))
            _FILTERS.append(inbound._topic_filter)  # see _FILTERS
        self.reader = DataReader(participant, inbound, qos=qos)
        self.waiting = ReadCondition(
            self.reader, ViewState.Any | InstanceState.Any | SampleState.NotRead
        )

    def _keep(self, sample: object) -> bool:
        """The topic filter (Cyclone's receive path): cheapest checks first, the MAC last."""
        why = "dropped_malformed"
        try:
            why = self._judge(sample)
        finally:  # a filter must answer, whatever the sample holds
            if why:
                with self._count_lock:
                    self.counts["ping_" + why] += 1
        return not why

    def _judge(self, sample: object) -> str:
        """Why ``sample`` is dropped ("" to keep it)."""
        assert self.ring is not None
        if not isinstance(sample, SealedSample) or not isinstance(sample.instance, str):
            return "dropped_malformed"
        sealed = bytes(sample.sealed)
        if not sample.instance.startswith(self._head) or sealed[1:2] != bytes([self.wanted]):
            return "ignored"
        try:
            claimed = parse(sealed, self.wanted)
        except InvalidFrameError:
            return "dropped_malformed"
        if sample.instance != ping_instance(self.topic, claimed.prefix):
            return "dropped_malformed"
        if self.admit is not None and not self.admit(claimed):
            return "dropped_stale"
        return "" if self.ring.verify(claimed) is True else "dropped_forged"

    def send(self, sealed: bytes) -> None:
        prefix, _ = claim(sealed)
        _write(self.writer, SealedSample(instance=ping_instance(self.topic, prefix), sealed=sealed))

    def take(self, kind: Kind) -> list[bytes]:
        """The waiting frames of ``kind`` about this topic (a rogue channel's others dropped)."""
        if not self.waiting.triggered:
            return []
        return [
            sealed
            for sample in _take(self.reader, PINGS_PER_CALL)
            if isinstance(sample.instance, str) and sample.instance.startswith(self._head)
            and len(sealed := bytes(sample.sealed)) > 1 and sealed[1] == kind
        ]  # fmt: skip

    def close(self) -> None:
        """Leave the channel: its reader (and with it the filter) and writer are deleted now,
        not whenever the garbage collector frees them (their callback stays pinned)."""
        for entity in (self.waiting, self.reader, self.writer):
            entity.__del__()

    def peers(self) -> int:
        """Ping endpoints matched (a new one may answer, or need an answer)."""
        status = self.writer.get_publication_matched_status()  # type: ignore[no-untyped-call]
        return int(status.current_count)


__all__ = ["PINGS_PER_CALL", "PING_TOPIC", "PingChannel", "ping_instance", "ping_qos"]
