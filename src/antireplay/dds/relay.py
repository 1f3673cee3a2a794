"""The announcement relay: a Cloud Discovery Service that cannot be replayed through.

Theory of operation
-------------------
Participants publish sealed announcements on the ingress topic
(:data:`ANNOUNCE_TOPIC`).  The relay opens each with its own
:class:`~antireplay.epochs.EpochVerifier` on a replay store
(``verifier_store``, e.g. SQLite, opened by :mod:`antireplay.wiring`; a replayed, forged or stale
announcement is refused there and renews nothing), and only an accepted one is
announced again on the egress topic (:data:`RELAYED_TOPIC`), sealed by the
relay's signer under its *service-name* prefix, carrying the origin's prefix
and epoch (:class:`RelayedAnnouncement`).  The signer's epoch ceiling lives in
a state file, so a relay restarted on the same host (or after a reboot)
resumes above everything it announced before.

Two relays must never share a service name: their announcements would share
one prefix and one would look like a replay of the other.  The relay watches
its own egress topic with a separate in-memory verifier: an *authentic* sample
under its own prefix that it never emitted (it remembers the digests of its
last samples, and each relay process stamps a random ``relay_id`` into what it
announces) can only come from a twin.
It is reported (error log, :attr:`AnnouncementRelay.twins`, the audit trail
with ``warning=DUPLICATE_SERVICE_NAME``),
and subscribers' verifiers count it as a prefix collision as well.
"""

from __future__ import annotations

import hashlib
import logging
import os
import struct
import threading
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass

from cyclonedds.domain import DomainParticipant

from antireplay.audit import AuditLog, AuditRow
from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import InvalidFrameError, StateUnavailableError, WarningCode
from antireplay.dds.config import MAX_AGE_S, MAX_FORWARD_S
from antireplay.dds.ping import PingListener
from antireplay.dds.topics import SealedReader, SealedWriter
from antireplay.dds.wire import SealedSample
from antireplay.epochs.policy import KeyRotation
from antireplay.epochs.sealing import SampleVerdict
from antireplay.state import ReplayStore
from antireplay.state.durable import DurableState

log = logging.getLogger("antireplay.dds.relay")

ANNOUNCE_TOPIC = "antireplay/announce"
RELAYED_TOPIC = "antireplay/relayed"
#: Epochs the relay remembers having emitted, to tell its own samples from a twin's.
EMITTED_MEMORY = 4096
#: Binding pings one :meth:`AnnouncementRelay.pump` judges at most.
PINGS_PER_PUMP = 256
_ORIGIN = struct.Struct(">8sQ8s")


@dataclass(frozen=True)
class RelayedAnnouncement:
    """What the relay re-announces: who announced, at which epoch, and what.

    ``relay_id`` is random per relay process: two relays sharing a service name
    (and a clock) can never emit byte-identical samples, so a twin always shows.
    """

    origin_prefix: bytes
    origin_epoch: int
    relay_id: bytes
    payload: bytes

    def encode(self) -> bytes:
        return _ORIGIN.pack(self.origin_prefix, self.origin_epoch, self.relay_id) + self.payload

    @classmethod
    def decode(cls, data: bytes) -> RelayedAnnouncement:
        if len(data) < _ORIGIN.size:
            raise InvalidFrameError("relayed announcement shorter than its origin header")
        prefix, epoch, relay_id = _ORIGIN.unpack_from(data)
        return cls(prefix, epoch, relay_id, data[_ORIGIN.size :])


@dataclass(frozen=True)
class TwinReport:
    """Another relay publishes authentic announcements under our service name."""

    service_name: str
    nonce_prefix: bytes
    epoch: int

    def line(self) -> str:
        return (
            f"DUPLICATE service name {self.service_name!r}: another relay announced epoch "
            f"{self.epoch} under our prefix {self.nonce_prefix.hex()}"
        )


class AnnouncementRelay:
    """Opens participants' announcements and re-announces the authentic, fresh ones."""

    def __init__(
        self,
        participant: DomainParticipant,
        psk: bytes,
        *,
        service_name: str,
        signer_state: DurableState,
        verifier_store: ReplayStore,
        ingress: str = ANNOUNCE_TOPIC,
        egress: str = RELAYED_TOPIC,
        clock: Clock | None = None,
        max_age_s: float = MAX_AGE_S,
        max_forward_s: float = MAX_FORWARD_S,
        audit: AuditLog | None = None,
        ping: PingListener | None = None,
        quiet: Callable[[], bool] | None = None,
        rotation: KeyRotation | None = None,
    ) -> None:
        self.service_name = service_name
        self._clock = resolve(clock)
        self.audit = audit
        self.ping = ping
        self.ingress = SealedReader(
            participant,
            ingress,
            psk,
            store=verifier_store,
            clock=self._clock,
            max_age_s=max_age_s,
            max_forward_s=max_forward_s,
            audit=audit,
            quiet=quiet,
            rotation=rotation,
        )
        self.egress = SealedWriter(
            participant,
            egress,
            psk,
            service_name=service_name,
            state=signer_state,
            clock=self._clock,
            max_forward_s=max_forward_s,  # the subscribers' bound: rotate, never be refused
            rotation=rotation,
        )
        self._watch = SealedReader(
            participant, egress, psk, clock=self._clock,
            max_age_s=max_age_s, max_forward_s=max_forward_s, rotation=rotation,
        )  # fmt: skip
        self.relay_id = os.urandom(8)
        self._emitted: deque[bytes] = deque(maxlen=EMITTED_MEMORY)
        self.relayed = 0
        self.twins: list[TwinReport] = []
        self.counts: Counter[str] = Counter()

    def close(self) -> None:
        """Release the relay's state (the signer's file lock; the stores are the opener's)."""
        for part in (self.ingress, self.egress, self._watch):
            part.close()

    def pump(self, timeout_s: float = 0.1) -> list[SampleVerdict]:
        """One round: answer fresh subscribers' challenges, judge waiting announcements,
        relay the accepted, look for a twin,
        judge at most ``PINGS_PER_PUMP`` waiting pings (a ping flood cannot stall the
        announcements)."""
        self.egress.answer_challenges()  # subscribers that just started need no fence
        verdicts = self.ingress.poll(timeout_s)
        for verdict in verdicts:
            if verdict.accepted:
                self._relay(verdict)
        for sample, seen in self._watch.take_judged():
            self._check_twin(sample, seen)
        if self.ping is not None:
            self.ping.drain(PINGS_PER_PUMP)
        return verdicts

    def serve(self, stop: threading.Event, period_s: float = 0.1) -> None:
        """Pump until ``stop`` is set."""
        while not stop.is_set():
            self.pump(period_s)

    def _relay(self, verdict: SampleVerdict) -> None:
        assert verdict.nonce_prefix is not None and verdict.epoch is not None
        body = RelayedAnnouncement(
            verdict.nonce_prefix, verdict.epoch, self.relay_id, verdict.value
        )
        sample = self.egress.seal(body.encode(), instance=verdict.instance)
        self._emitted.append(_digest(sample))
        self.egress.publish(sample)
        self.relayed += 1

    def _check_twin(self, sample: SealedSample, seen: SampleVerdict) -> None:
        """An authentic sample under our prefix that we did not emit comes from a twin."""
        if seen.nonce_prefix != self.egress.nonce_prefix or not seen.authentic:
            return
        if _digest(sample) in self._emitted:
            return
        assert seen.epoch is not None
        report = TwinReport(self.service_name, seen.nonce_prefix, seen.epoch)
        self.twins.append(report)
        self.counts["duplicate_service_name"] += 1
        log.error("%s", report.line())
        if self.audit is not None:
            self._audit_twin(report)

    def _audit_twin(self, report: TwinReport) -> None:
        assert self.audit is not None
        try:
            self.audit.append(
                AuditRow(
                    self._clock.wall(),
                    "alert",
                    warning=WarningCode.DUPLICATE_SERVICE_NAME,
                    sender=report.nonce_prefix.hex(),
                    sender_verified=True,
                    msg_id=str(report.epoch),
                )
            )
        except StateUnavailableError:
            self.counts["audit_unavailable"] += 1
            log.error("audit trail unavailable; the twin report was not recorded")


def _digest(sample: SealedSample) -> bytes:
    return hashlib.sha256(bytes(sample.sealed)).digest()[:16]
