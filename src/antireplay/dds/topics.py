"""Sealed topics on Cyclone DDS: the writer, the reader and the challenge channel (the driver).

Theory of operation
-------------------
On the wire a sealed topic has one DDS type, :class:`SealedSample`: the instance key
(a DDS key field) and an :mod:`antireplay.epochs` announcement framed and judged by the
pure core :mod:`antireplay.epochs.sealing` (topic key, framing, the check before any
crypto, the :class:`SampleVerdict` of each sample).  This module does the I/O around it:
Cyclone DDS endpoints, the signer's and verifier's state, the lock, the audit trail.

A reader judges each sample cheapest first: :func:`~antireplay.epochs.sealing.check`
(no crypto, no state), then :meth:`EpochVerifier.open` (MAC, freshness,
``epoch > last[prefix]``, then one ``advance`` on the replay store, durable before it
returns), and only then is the data decoded and handed over.

**Start fence.**  A reader refuses every sample sealed before it started (plus
``max_forward_s``) unless its store proves otherwise: a memory store cannot know what a
previous process accepted; a SQLite store that survived sets no fence.  A fenced reader
does not wait it out: it sends a challenge on :data:`PING_TOPIC` (:mod:`.challenge`:
authenticated on arrival, one slot set per sender; when
:class:`~antireplay.epochs.sealing.ChallengeTimer` says), every writer answers in its
next :meth:`SealedWriter.write`, and the reader accepts that writer's epochs above the
answer at once (captures stay refused; :mod:`antireplay.epochs.policy`).  Every refusal
is counted in :attr:`SealedReader.counts` and recorded through the rate-limited
:class:`~antireplay.audit.RefusalAuditor` (authentic refusals on their own budget).
Stores, state files and the audit trail are built by :mod:`antireplay.wiring` and handed in.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from antireplay.audit import AuditLog, RefusalAuditor
from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import (
    Code,
    ReplayAttackError,
    StateUnavailableError,
)
from antireplay.dds.challenge import PING_TOPIC, PingChannel
from antireplay.dds.config import MAX_AGE_S, MAX_FORWARD_S
from antireplay.dds.wire import SealedSample
from antireplay.epochs import Announcement, EpochSigner, EpochVerifier, Kind, sealing
from antireplay.epochs.policy import (
    NONCE_LEN,
    Claim,
    KeyRing,
    KeyRotation,
    to_ns,
)
from antireplay.epochs.sealing import RAW, ChallengeTimer, SampleVerdict, claim, topic_key
from antireplay.state import ReplayStore
from antireplay.state.durable import DurableState
from antireplay.state.memory import MemoryStore

log = logging.getLogger("antireplay.dds")

#: The name of earlier releases for :class:`~antireplay.epochs.sealing.SampleVerdict`.
Verdict = SampleVerdict
#: Refusals audited per second, per class (:class:`~antireplay.audit.RefusalAuditor`).
AUDIT_PER_S = 50.0


def default_qos(depth: int = 256) -> Qos:
    """Reliable, keep-last ``depth`` per instance: a sealed topic's defaults."""
    return Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(depth))


def _domain_of(participant: Any) -> int:
    domain = getattr(participant, "domain_id", 0)
    return int(domain) if isinstance(domain, int) else 0


def type_name_of(data_type: type[IdlStruct] | None) -> str:
    return RAW if data_type is None else str(data_type.__idl_typename__)


def _topic(participant: DomainParticipant, name: str, qos: Qos) -> Topic[SealedSample]:
    return Topic(participant, name, SealedSample, qos=qos)


def matched_readers(writer: DataWriter[Any]) -> int:
    """How many readers match ``writer``, from its matched status: the list call races a
    peer joining (its count can outgrow the list it filled) and raises IndexError."""
    status = writer.get_publication_matched_status()  # type: ignore[no-untyped-call]
    return int(status.current_count)


def matched_writers(reader: DataReader[Any]) -> int:
    """How many writers match ``reader`` (the status, as :func:`matched_readers`)."""
    status = reader.get_subscription_matched_status()  # type: ignore[no-untyped-call]
    return int(status.current_count)


class SealedWriter:
    """A DDS writer whose every sample is sealed with a strictly increasing epoch."""

    def __init__(
        self,
        participant: DomainParticipant,
        topic: str,
        psk: bytes,
        *,
        data_type: type[IdlStruct] | None = None,
        nonce_prefix: bytes | None = None,
        service_name: str | None = None,
        state: DurableState | None = None,
        clock: Clock | None = None,
        reserve_s: float = 1.0,
        max_forward_s: float = MAX_FORWARD_S,
        qos: Qos | None = None,
        rotation: KeyRotation | None = None,
    ) -> None:
        self.topic_name, self.data_type = topic, data_type
        self.counts: Counter[str] = Counter()
        self._clock = resolve(clock)
        self._max_forward_ns = to_ns(max_forward_s)
        type_name, domain = type_name_of(data_type), _domain_of(participant)
        key = topic_key(psk, topic, type_name, domain)
        topic_rotation = rotated_for(rotation, topic, type_name, domain)
        # max_forward_s: the readers' bound (their default unless configured), so a forward
        # clock glitch the readers would refuse makes this writer rotate its prefix instead
        # of being refused until real time catches up.
        self.signer = EpochSigner(
            key,
            nonce_prefix=nonce_prefix,
            service_name=service_name,
            state=state,
            clock=self._clock,
            reserve_s=reserve_s,
            max_forward_s=max_forward_s,
            rotation=topic_rotation,
        )
        qos = qos or default_qos()
        self._writer = DataWriter(participant, _topic(participant, topic, qos), qos=qos)
        self._pings = PingChannel(
            participant, topic, KeyRing(key, topic_rotation), wanted=Kind.CHALLENGE,
            admit=self._timely, counts=self.counts,
        )  # fmt: skip

    def _timely(self, challenge: Claim) -> bool:
        """A challenge worth a look: sent within ``max_forward_s`` of our clock (what
        :meth:`EpochSigner.answer` checks again), carrying a nonce's length."""
        ahead = challenge.epoch - to_ns(self._clock.wall())
        return abs(ahead) <= self._max_forward_ns and len(challenge.payload) == NONCE_LEN

    @property
    def nonce_prefix(self) -> bytes:
        return self.signer.nonce_prefix

    def answer_challenges(self) -> int:
        """Answer the waiting challenges of fresh readers (each at a new epoch); a refused
        one is counted (``challenge_<outcome>``) and spends nothing.  :meth:`write` calls
        this first, so a writer answers within one period of its own; returns the count."""
        if not self._pings.waiting.triggered:  # the common case: nothing to answer
            return 0
        answered = 0
        for challenge in self._pings.take(Kind.CHALLENGE):
            try:
                self._pings.send(self.signer.answer(challenge))
            except ReplayAttackError as exc:
                self.counts["challenge_" + sealing.OUTCOMES.get(type(exc), "refused")] += 1
                continue
            answered += 1
        self.counts["challenge_answered"] += answered
        return answered

    def seal(self, value: bytes | IdlStruct, *, instance: str = "") -> SealedSample:
        """The sealed sample for ``value`` (not yet written): each call takes a new epoch."""
        data = value if isinstance(value, bytes) else value.serialize()
        return SealedSample(
            instance=instance, sealed=self.signer.seal(sealing.frame(instance, data))
        )

    def write(self, value: bytes | IdlStruct, *, instance: str = "") -> SealedSample:
        """Answer waiting challenges, then seal and publish one sample."""
        self.answer_challenges()
        sample = self.seal(value, instance=instance)
        self._writer.write(sample)
        return sample

    def publish(self, sample: SealedSample) -> None:
        """Publish an already sealed sample (a relay's or a test's own)."""
        self._writer.write(sample)

    def flush(self, timeout_s: float = 2.0) -> bool:
        """Wait until matched readers acknowledged everything written (reliable QoS);
        ``False`` when they did not in time."""
        try:
            return bool(self._writer.wait_for_acks(duration(seconds=timeout_s)))
        except AttributeError:  # cyclonedds 0.10's DataWriter reports a timeout this way
            return False

    def matched_readers(self) -> int:
        return matched_readers(self._writer)

    def challenge_peers(self) -> int:
        """Other endpoints on the challenge channel (fenced readers, other writers): only
        then may a challenge be on its way (our own channel matches itself)."""
        return max(0, matched_writers(self._pings.reader) - 1)

    def close(self) -> None:
        """Release the signer's state file (its owner lock), as a stopping process does."""
        self.signer.close()

    def wait_for_readers(self, count: int = 1, timeout_s: float = 10.0) -> bool:
        """Bounded wait until ``count`` readers matched (DDS drops samples nobody matched)."""
        deadline = time.monotonic() + timeout_s
        while self.matched_readers() < count:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True


class SealedReader:
    """A DDS reader that hands over only authentic, fresh samples and judges the rest."""

    def __init__(
        self,
        participant: DomainParticipant,
        topic: str,
        psk: bytes,
        *,
        data_type: type[IdlStruct] | None = None,
        store: ReplayStore | None = None,
        clock: Clock | None = None,
        max_age_s: float = MAX_AGE_S,
        max_forward_s: float = MAX_FORWARD_S,
        audit: AuditLog | None = None,
        qos: Qos | None = None,
        challenge: bool = True,
        quiet: Callable[[], bool] | None = None,
        rotation: KeyRotation | None = None,
    ) -> None:
        self.topic_name, self.data_type = topic, data_type
        self._decode = None if data_type is None else data_type.deserialize
        self._clock = resolve(clock)
        type_name, domain = type_name_of(data_type), _domain_of(participant)
        self._own_store = store is None  # in memory, as large as ``open_store("memory")``
        self.verifier = EpochVerifier(
            topic_key(psk, topic, type_name, domain),
            store=MemoryStore(clock=self._clock) if store is None else store,
            namespace=f"dds:{domain}:{topic}:{type_name}",
            max_age_s=max_age_s,
            max_forward_s=max_forward_s,
            clock=self._clock,
            rotation=rotated_for(rotation, topic, type_name, domain),
        )
        self.audit = audit
        self.counts: Counter[str] = Counter()
        self._refusals = refusal_auditor(self._clock, audit, self.counts, quiet)
        self._lock = threading.Lock()
        qos = qos or default_qos()
        self._reader = DataReader(participant, _topic(participant, topic, qos), qos=qos)
        self._waitset = WaitSet(participant)
        self._waitset.attach(
            ReadCondition(self._reader, ViewState.Any | InstanceState.Any | SampleState.NotRead)
        )
        self._pings: PingChannel | None = None
        #: The nonces of the challenges sent (a snapshot the ping filter reads lock-free).
        self._nonces: frozenset[bytes] = frozenset()
        if challenge and self.verifier.fenced():
            self._pings = PingChannel(
                participant, topic, self.verifier.policy.ring, wanted=Kind.ANSWER,
                admit=lambda answer: answer.payload in self._nonces, counts=self.counts,
            )  # fmt: skip
            self._waitset.attach(self._pings.waiting)
        self._timer = ChallengeTimer()

    def matched_writers(self) -> int:
        return matched_writers(self._reader)

    def close(self) -> None:
        """Write the folded refusals' summaries, as a stopping process does; the store is
        closed by whoever opened it (this reader, for its default memory store)."""
        self._refusals.close()
        if self._own_store:
            self.verifier.store.close()

    def judge(self, sample: SealedSample) -> SampleVerdict:
        """Check, authenticate, commit one sample; never raises for hostile input."""
        with self._lock:
            verdict = self._judge(sample)
        self.counts[verdict.outcome] += 1
        if verdict.code is not None:  # refused
            log.debug("refused sample on %s: %s", self.topic_name, verdict.line())
            record_refusal(self._refusals, verdict, f"dds {self.topic_name}", self.counts)
        return verdict

    def _judge(self, sample: SealedSample) -> SampleVerdict:
        instance = sample.instance if isinstance(sample.instance, str) else ""
        sealed = sample.sealed
        if not isinstance(sealed, bytes):  # as Cyclone hands a sequence<uint8> over: ints
            sealed = bytes(sealed)
        early = sealing.check(instance, sealed)
        if early is not None:
            return early
        opened = open_judged(self.verifier, sealed, Kind.ANNOUNCEMENT, instance)
        if isinstance(opened, SampleVerdict):
            return opened.named("sample")
        return sealing.accepted(instance, opened, self._decode)

    def take(self, limit: int = 256) -> list[SampleVerdict]:
        """Judge every sample waiting (up to ``limit``)."""
        return [verdict for _, verdict in self.take_judged(limit)]

    def take_judged(self, limit: int = 256) -> list[tuple[SealedSample, SampleVerdict]]:
        """Like :meth:`take`, keeping each wire sample beside its verdict (a fenced reader
        first judges waiting answers and sends a challenge when one is due)."""
        if self._pings is not None:
            self._freshen(self._pings)
        samples = self._reader.take(N=limit)
        return [(s, self.judge(s)) for s in samples if isinstance(s, SealedSample)]

    def _freshen(self, pings: PingChannel) -> None:
        """Judge the answers waiting; challenge when the timer says so; once past the start
        fence, leave the ping topic for good."""
        for sealed in pings.take(Kind.ANSWER):
            self._answer(sealed)
        if not self.verifier.fenced():
            self._waitset.detach(pings.waiting)
            pings.close()
            self._pings = None
            return
        if self._timer.due(pings.peers(), self._clock.monotonic()):
            challenge = self.verifier.challenge()
            if challenge is not None:
                self._nonces = frozenset(self.verifier.policy.nonces)  # before any answer
                pings.send(challenge)
                self.counts["challenge_sent"] += 1

    def _answer(self, sealed: bytes) -> None:
        """One answer: check, authenticate, commit (the verifier); a forged one is counted
        and audited, one for a nonce we are not waiting for (another reader's) counted."""
        with self._lock:
            opened = open_judged(self.verifier, sealed, Kind.ANSWER, self.topic_name)
        if isinstance(opened, Announcement):
            self.counts["answer_accepted"] += 1
            return
        self.counts["answer_" + opened.outcome] += 1
        if opened.outcome != "stale":
            record_refusal(self._refusals, opened, self.topic_name, self.counts)

    def wait(self, timeout_s: float) -> None:
        """Block until data may be waiting, or ``timeout_s``."""
        self._waitset.wait(duration(seconds=timeout_s))

    def poll(self, timeout_s: float = 0.1) -> list[SampleVerdict]:
        """Wait up to ``timeout_s`` for data, then judge what arrived."""
        verdicts = self.take()
        if not verdicts:
            self.wait(timeout_s)
            verdicts = self.take()
        return verdicts


def rotated_for(
    rotation: KeyRotation | None, topic: str, type_name: str, domain: int
) -> KeyRotation | None:
    """The fleet key's rotation as one topic sees it: the successor's topic key."""
    if rotation is None:
        return None
    return KeyRotation(topic_key(rotation.next_psk, topic, type_name, domain), rotation.cutover_ns)


def refusal_auditor(
    clock: Clock,
    audit: AuditLog | None,
    counts: Counter[str],
    quiet: Callable[[], bool] | None = None,
) -> RefusalAuditor:
    """The rate-limited auditor of a reader's or listener's refusals; what it folds is
    counted in ``counts`` as ``audit_rate_limited``; while ``quiet()`` (free space under
    the trail below its first floor) refusals are counted, not written."""
    return RefusalAuditor(audit, clock, per_s=AUDIT_PER_S, counts=counts, quiet=quiet)


def record_refusal(
    auditor: RefusalAuditor, verdict: SampleVerdict, where: str, counts: Counter[str]
) -> None:
    """One row for a refusal (sender = claimed prefix; never the payload), authentic
    refusals on their own budget; a trail that is down is counted and logged."""
    try:
        auditor.record(
            code=str(verdict.code),
            sender=None if verdict.nonce_prefix is None else verdict.nonce_prefix.hex(),
            sender_verified=verdict.authentic,
            warning=f"{where}: {verdict.outcome}",
            msg_id=None if verdict.epoch is None else str(verdict.epoch),
        )
    except StateUnavailableError:
        counts["audit_unavailable"] += 1
        log.error("audit trail unavailable; a %s refusal was not recorded", where)


def open_judged(
    verifier: EpochVerifier, sealed: bytes, kind: Kind, instance: str
) -> Announcement | SampleVerdict:
    """``verifier.open`` with every refusal turned into a typed :class:`SampleVerdict`."""
    collisions = verifier.prefix_collisions
    try:
        if kind is Kind.ANSWER:
            return verifier.open_answer(sealed)
        return verifier.open(sealed, kind=kind)
    except ReplayAttackError as exc:
        collided = verifier.prefix_collisions != collisions
        return sealing.refused(exc, instance, sealed, collided=collided)
    except OSError as exc:  # the store could not persist the epoch: fail closed
        reason = f"verifier state not persisted: {exc.strerror or exc}"
        return SampleVerdict("state_unavailable", Code.STATE_UNAVAILABLE, reason, instance)


__all__ = [
    "PING_TOPIC",
    "PingChannel",
    "SampleVerdict",
    "SealedReader",
    "SealedSample",
    "SealedWriter",
    "Verdict",
    "claim",
    "record_refusal",
    "refusal_auditor",
    "rotated_for",
    "topic_key",
]
