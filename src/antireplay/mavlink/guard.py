"""MAVLink v2 signing guard: the driver of :mod:`antireplay.mavlink.policy`.

Theory of operation
-------------------
Two phases, as everywhere: :meth:`MavlinkGuard.check` records nothing, :meth:`MavlinkGuard.open`
checks, authenticates, commits.  A frame is parsed once (:func:`~.codec.parse_frame`; a router
hands the :class:`~.codec.Frame` its transport parsed) and judged by the policy: direction,
allow-list and the timestamp rules from memory (so a replay costs no HMAC), then a
constant-time **verify** -> ``SIGNATURE_INVALID`` (nothing before it touches the stream
table, so a forged ``2**48 - 1`` jams nothing), **bind** ``target_system`` ->
``WRONG_TARGET``, and **commit**: the policy judges again and answers "accepted" or what
must be read or made durable first; the guard does that store I/O and asks again (persist,
then believe).  The guard's lock is held only around policy calls, never across store I/O;
lease writes (claim, renew, release) are serialized among themselves.

Persistence: a lease and a restart fence, not an fsync per frame.  MAVLink timestamps are
wall-anchored, so the store keeps a **lease** (accepts only while ``now <= lease``, renewed
by :meth:`MavlinkGuard.tick`, which its owner's timer calls every ``persist_interval_s``:
the router's one timer for all its guards), ``high`` (the highest timestamp accepted past
the lease, by whole seconds, written before accepting a frame that exceeds it) and each
stream's high-water.  At start the restart fence is ``max(previous lease expiry, high)``:
everything accepted before a stop or ``kill -9`` is refused, and a frame once accepted
ahead of the clock fences only until the wall clock passes its timestamp; after a crash
the lease is claimed once the old one has expired (no waiting in
:meth:`MavlinkGuard.start`: the owner's timer tries again).  A lost store fences at the
loss time plus ``max_forward_s``; :meth:`MavlinkGuard.fenced_until` says until when.  The
lease is exclusive (odd/even generations through ``advance``): a second guard on one prefix
is ``STATE_UNAVAILABLE`` until it takes over; guards *active at once* use
``write_through=True`` (one store write per frame).
"""

from __future__ import annotations

import hashlib
import hmac
import threading
from dataclasses import dataclass

from antireplay.core.clock import Clock, resolve
from antireplay.core.errors import (
    ReplayAttackError,
    SignatureInvalidError,
    StateUnavailableError,
)
from antireplay.mavlink.codec import MAV_EPOCH, UNITS_PER_S, Frame, mav_time, parse_frame
from antireplay.mavlink.policy import Facts, FrameAdmission, MavPolicy, Persist
from antireplay.state import ReplayStore

__all__ = ["FrameAdmission", "MavVerdict", "MavlinkGuard"]

_MAX_STEPS = 8  # Persist steps one frame may need (claim, lookup, renew, high, through)


@dataclass(frozen=True, slots=True)
class MavVerdict:
    """An accepted frame."""

    stream: tuple[int, int, int]
    msgid: int
    timestamp: int
    signed: bool
    frame: Frame  # the parsed frame, so that an adapter routes without parsing it again


class MavlinkGuard:
    """Judges MAVLink v2 frames: :meth:`check` records nothing, :meth:`open` checks,
    verifies, binds and commits (module docstring).

    With a store, call :meth:`start` before the first frame (it claims the lease if it
    is free; a first frame claims lazily otherwise), :meth:`tick` every
    ``persist_interval_s`` (flush and renew) and :meth:`stop` after the last (it flushes
    and releases).
    """

    def __init__(
        self,
        key: bytes,
        *,
        store: ReplayStore | None = None,
        clock: Clock | None = None,
        system_id: int | None = None,
        allow_unsigned: frozenset[int] = frozenset(),
        allow_v1: frozenset[int] = frozenset(),
        max_streams: int = 256,
        reorder_window: int = 0,
        new_stream_max_age_s: float = 60.0,
        max_forward_s: float = 60.0,
        store_prefix: str = "mav",
        write_through: bool = False,
        persist_interval_s: float = 1.0,
        lease_skew_s: float = 0.25,
    ) -> None:
        if len(key) != 32:
            raise ValueError("a MAVLink signing key is 32 bytes")
        if persist_interval_s <= 0:
            raise ValueError("persist_interval_s must be positive")
        self._key = key
        self.store = store
        self.clock = resolve(clock)
        self.system_id = system_id
        self.prefix = store_prefix
        self.write_through = write_through
        self.persist_interval_s = persist_interval_s
        self.policy = MavPolicy(
            system_id=system_id,
            allow_unsigned=allow_unsigned,
            allow_v1=allow_v1,
            max_streams=max_streams,
            reorder_window=reorder_window,
            new_stream_max_age=int(new_stream_max_age_s * UNITS_PER_S),
            max_forward=int(max_forward_s * UNITS_PER_S),
            stored=store is not None,
            periodic=store is not None and not write_through,
            lease_len=int(2 * persist_interval_s * UNITS_PER_S),
            lease_skew=int(lease_skew_s * UNITS_PER_S),
            prefix=store_prefix,
        )
        self.counts = self.policy.counts
        self._lock = threading.Lock()  # around policy calls only
        self._lease_io = threading.Lock()  # serializes the lease's store writes

    def __len__(self) -> int:
        return len(self.policy.streams)

    @property
    def periodic(self) -> bool:
        """Whether this guard persists periodically behind a lease (module docstring)."""
        return self.policy.periodic

    @property
    def allow_unsigned(self) -> frozenset[int]:
        return self.policy.allow_unsigned

    @property
    def allow_v1(self) -> frozenset[int]:
        return self.policy.allow_v1

    @property
    def reorder_window(self) -> int:
        return self.policy.reorder_window

    @property
    def max_forward(self) -> int:
        return self.policy.max_forward

    @property
    def new_stream_max_age(self) -> int:
        return self.policy.new_stream_max_age

    @property
    def refused_sources(self) -> set[int]:
        """Source system ids that belong to the other direction (the policy's)."""
        return self.policy.refused_sources

    @property
    def restart_fence(self) -> int:
        """Timestamps at or below this are refused (module docstring)."""
        return self.policy.restart_fence

    def fenced_until(self) -> tuple[float, str] | None:
        """While the restart fence lies ahead of the clock: until when (wall seconds) and
        why (:attr:`MavPolicy.fence_cause <antireplay.mavlink.policy.MavPolicy.fence_cause>`);
        ``None`` once a frame stamped now passes it."""
        fence = self.policy.restart_fence
        until = MAV_EPOCH + fence / UNITS_PER_S
        if fence < 0 or self.clock.wall() > until:
            return None
        return until, self.policy.fence_cause

    @property
    def claimed(self) -> bool:
        """Whether this guard holds its lease (always true without periodic persistence)."""
        return not self.periodic or bool(self.policy.generation)

    def check(self, raw: bytes | Frame) -> Frame:
        """Records nothing: parse (unless given a parsed frame), direction, allow-list and
        every stream rule a replay fails, before any cryptography."""
        frame = raw if isinstance(raw, Frame) else parse_frame(raw)
        now = mav_time(self.clock)
        with self._lock:
            self.policy.check(frame, now)
        return frame

    def admit(self, raw: bytes | Frame, *, trusted: bool, own_link_id: int) -> FrameAdmission:
        """Records nothing: what a frame a router received for this guard needs before
        :meth:`open` (:meth:`MavPolicy.admit <antireplay.mavlink.policy.MavPolicy.admit>`)."""
        frame = raw if isinstance(raw, Frame) else parse_frame(raw)
        return self.policy.admit(frame, trusted=trusted, own_link_id=own_link_id)

    def bind_direction(self, verdict: MavVerdict) -> None:
        """The other side of the link authenticated ``verdict``: its source system belongs
        there and is refused here from now on (an unsigned frame teaches nothing)."""
        if verdict.signed:
            with self._lock:
                self.policy.bind_direction(verdict.frame)

    def open(self, raw: bytes | Frame) -> MavVerdict:
        """Check, verify the signature, bind, commit: accept one frame or raise a typed
        :class:`ReplayAttackError`.  Of two racers on one timestamp exactly one passes."""
        frame = raw if isinstance(raw, Frame) else parse_frame(raw)
        now = mav_time(self.clock)
        policy = self.policy
        with self._lock:
            policy.check(frame, now)
        if not frame.signed:
            policy.bind(frame)
            return MavVerdict(frame.stream, frame.msgid, 0, False, frame)
        data = frame.raw
        expected = hashlib.sha256(self._key + data[:-6]).digest()[:6]
        if not hmac.compare_digest(expected, data[-6:]):
            raise SignatureInvalidError("MAVLink signature does not verify")
        policy.bind(frame)
        facts: Facts | None = None
        for _ in range(_MAX_STEPS):
            with self._lock:
                step = policy.commit(frame, now, facts)
            if step is None:
                return MavVerdict(frame.stream, frame.msgid, frame.timestamp, True, frame)
            facts = self._persist(step, now, facts or Facts())
        raise StateUnavailableError(f"the MAVLink state {self.prefix!r} kept moving")

    def _persist(self, step: Persist, now: int, facts: Facts) -> Facts:
        """Do what the policy asked before it commits a frame (store I/O, no lock held)."""
        store = self._persistent_store()
        if step.claim:
            self._acquire(now)
        elif step.lookup is not None:
            facts.stored[step.lookup] = store.current(step.lookup)
        elif step.renew:
            self.counts["frame_path_renewals"] += 1
            self._renew(now)
        elif step.high is not None:
            store.advance(self.policy.high_key, step.high)
            with self._lock:
                self.policy.high_persisted(step.high)
        elif step.through is not None:
            facts.through = store.advance(*step.through)
        return facts

    # --- lifecycle: lease, flush -----------------------------------------------------------

    def start(self) -> None:
        """Claim the lease if it is free (no waiting: ``STATE_UNAVAILABLE`` while another
        holds it; the owner's timer tries again through :meth:`tick`).  No-op without
        periodic persistence."""
        if self.periodic and not self.policy.generation:
            self._acquire(mav_time(self.clock))

    def tick(self) -> None:
        """The owner's timer, every ``persist_interval_s``: claim the lease if it is not
        held yet, else persist the streams that moved and renew it."""
        if not self.periodic:
            return
        if not self.policy.generation:
            self.start()
            return
        self.flush()

    def stop(self) -> None:
        """Persist what is dirty and release the lease (clean stop)."""
        if not self.periodic:
            return
        self.flush()
        with self._lease_io:
            with self._lock:
                released = self.policy.release(mav_time(self.clock))
            if released is not None:
                self._persistent_store().advance(self.policy.lease_key, released)

    def flush(self) -> None:
        """Persist the streams that moved and renew the lease (:meth:`tick` calls this)."""
        if not self.periodic:
            return
        with self._lock:
            dirty = self.policy.take_dirty()
        store = self._persistent_store()
        try:
            for key, value in dirty.items():
                store.advance(key, value)
        except BaseException:
            with self._lock:
                self.policy.restore_dirty(dirty)
            raise
        self.counts["flushes"] += 1
        if self.policy.generation:
            self._renew(mav_time(self.clock))

    def tick_safely(self) -> None:
        """:meth:`tick` for a timer: a store that is down or a lease lost is counted, and
        the frame path fails closed."""
        try:
            self.tick()
        except ReplayAttackError:
            self.counts["persist_failures"] += 1

    def _persistent_store(self) -> ReplayStore:
        if self.store is None:
            raise StateUnavailableError("no store configured")
        return self.store

    def _acquire(self, now: int) -> None:
        """Claim the lease and raise the restart fence."""
        store, policy = self._persistent_store(), self.policy
        with self._lease_io:
            if policy.generation:
                return  # another thread claimed it meanwhile
            found = store.current(policy.lease_key)
            high = store.current(policy.high_key)
            ahead = None if high is not None else store.current(policy.ahead_key)
            migrate = policy.migration(found, high, ahead)
            if migrate is not None:  # the previous version's margin, written before the claim
                store.advance(policy.high_key, migrate)
                high = store.current(policy.high_key)
                with self._lock:
                    policy.high_persisted(migrate)
            lost = store.verify().fence
            with self._lock:
                value = policy.claim(found, high, lost, now)
            written = store.advance(policy.lease_key, value)
            with self._lock:
                policy.claimed(value, written)

    def _renew(self, now: int) -> None:
        """Extend the lease to ``now + 2 intervals``; losing it to another guard fails closed."""
        store, policy = self._persistent_store(), self.policy
        with self._lease_io:
            with self._lock:
                value = policy.renewal(now)
            written = store.advance(policy.lease_key, value)
            found = None if written else store.current(policy.lease_key)
            with self._lock:
                policy.renewed(value, written, found)
