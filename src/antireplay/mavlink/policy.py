"""MAVLink replay policy: a parsed frame and a time in; a refusal, a step to persist, or done.

Theory of operation
-------------------
Sans-I/O: no store, audit, socket, thread, lock, log or clock read.  The driver
(:mod:`antireplay.mavlink.guard`) serializes the calls, holds its lock only around them,
performs every store read and write between them, and reports what it found back.

:meth:`MavPolicy.check` records nothing: **direction** (a source system of the other side,
:meth:`MavPolicy.bind_direction`) -> ``WRONG_DIRECTION``; unsigned frames only if
allow-listed -> ``SIGNATURE_REQUIRED``; **timestamp rules** from memory only (ahead of
``max_forward``, at or below the restart fence, not above the stream's last, below the
table's eviction fence), so a replay costs no HMAC.  :meth:`MavPolicy.bind` refuses a
frame addressed to another vehicle (``WRONG_TARGET``).  :meth:`MavPolicy.admit` says what
a router's link needs before judging (sign on a trusted tool's behalf; refuse the router's
own link id from a ground link).

:meth:`MavPolicy.commit` judges again and either commits in memory (``None``: accepted) or
returns :class:`Persist`: what must be read or made durable first (claim the lease, a new
stream's stored high-water, renew a lapsed lease, raise the persisted highest timestamp,
or, written through, advance the stream).  The driver does it, reports it in
:class:`Facts` (or via :meth:`claimed`, :meth:`renewed`, :meth:`high_persisted`) and calls
``commit`` again: persist, then believe.  Of two racers on one timestamp the second is
refused by the re-judgement.  **Lease arithmetic**: the lease value is ``generation *
2**42 + expiry in ms``; odd generations are held, even released; a claim is refused while
an odd lease is live (plus ``lease_skew``).  The restart fence is a *timestamp*, never a
margin: the previous lease's expiry (a clean stop writes the highest timestamp accepted),
the persisted highest timestamp (``high``: written, by whole seconds, before accepting a
frame stamped past the held lease) and after a store data loss the loss time plus
``max_forward``.  A clock spike fences only until the wall clock passes it.  The previous
version's margin (``ahead``) is converted while ``high`` is absent (:meth:`migration`: the
expiry of the lease it wrote plus ``ahead``) and written as ``high`` before the claim.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from antireplay.core.counters import CounterWindow, FencedTable
from antireplay.core.errors import (
    CounterReplayedError,
    MessageFromFutureError,
    MessageStaleError,
    SignatureRequiredError,
    StateUnavailableError,
    WrongDirectionError,
    WrongTargetError,
)
from antireplay.core.messages import StrEnum
from antireplay.core.window import NEVER
from antireplay.mavlink.codec import MAV_EPOCH, TS_LIMIT, UNITS_PER_S, Frame, target_system

MS = UNITS_PER_S // 1000  # the lease's expiry is stored in milliseconds
GENERATION = 2**42  # lease value = generation * 2**42 + expiry (ms): 139 years of expiry
HIGH_STEP = UNITS_PER_S  # the persisted highest timestamp rises by whole seconds
_CAUSES = ("lease", "high", "lost")  # a restart fence's causes, the most telling last


class RestartFenceError(MessageStaleError):
    """At or below the restart fence: the previous run may have accepted it (a driver
    summarises these instead of reporting each one); ``below_s``: how far below."""

    below_s: float = 0.0


class FrameAdmission(StrEnum):
    """What a frame from a router's link needs before its guard judges it."""

    JUDGE = "judge"  # as it came
    SIGN = "sign"  # an unsigned v2 frame from a trusted tool: sign it on its behalf, then judge


@dataclass(frozen=True, slots=True)
class Persist:
    """What the driver must do before asking :meth:`MavPolicy.commit` again (one of)."""

    claim: bool = False  # the lease is not held: claim it (:meth:`MavPolicy.claim`)
    lookup: str | None = None  # a new stream: read this key's stored high-water
    renew: bool = False  # the lease has lapsed: renew it (:meth:`MavPolicy.renewal`)
    high: int | None = None  # advance the highest-timestamp key to this timestamp
    through: tuple[str, int] | None = None  # write-through: advance this key to this value


@dataclass(slots=True)
class Facts:
    """What the driver read or wrote for one frame's :class:`Persist` steps."""

    stored: dict[str, int | None] = field(default_factory=dict)
    through: bool | None = None  # the write-through advance's answer


@dataclass(slots=True)
class _Stream:
    """A stream's entry beside its high-water mark in the table (the mark is ``last``)."""

    floor: int = -1  # restored from a store: everything at or below was (or may have been) seen
    window: CounterWindow | None = None


def lease_value(generation: int, until: int) -> int:
    """The stored lease: ``generation`` and an expiry (MAVLink units, rounded up to ms)."""
    return generation * GENERATION + -(-until // MS)


def lease_parts(value: int) -> tuple[int, int]:
    """``(generation, expiry in MAVLink units)`` of a stored lease value."""
    generation, until_ms = divmod(value, GENERATION)
    return generation, until_ms * MS


class MavPolicy:
    """The rules and the in-memory state of one guard (module docstring); not thread-safe:
    the driver serializes every call."""

    def __init__(
        self,
        *,
        system_id: int | None = None,
        allow_unsigned: frozenset[int] = frozenset(),
        allow_v1: frozenset[int] = frozenset(),
        max_streams: int = 256,
        reorder_window: int = 0,
        new_stream_max_age: int = 60 * UNITS_PER_S,
        max_forward: int = 60 * UNITS_PER_S,
        stored: bool = False,
        periodic: bool = False,
        lease_len: int = 2 * UNITS_PER_S,
        lease_skew: int = UNITS_PER_S // 4,
        prefix: str = "mav",
    ) -> None:
        self.system_id = system_id
        self.allow_unsigned = allow_unsigned
        self.allow_v1 = allow_v1 & allow_unsigned
        self.reorder_window = reorder_window
        self.new_stream_max_age, self.max_forward = new_stream_max_age, max_forward
        self.stored, self.periodic = stored, periodic
        self.lease_len, self.lease_skew, self.prefix = lease_len, lease_skew, prefix
        #: Source system ids that belong to the other direction (:meth:`bind_direction`).
        self.refused_sources: set[int] = set() if system_id is None else {system_id}
        self.streams: FencedTable[tuple[int, int, int], _Stream] = FencedTable(max_streams)
        self.counts: Counter[str] = Counter()
        self.generation = 0  # odd while this guard holds the lease, 0 when it does not
        self.lease = -1  # frames are accepted only while now <= lease
        self.saved_high = -1  # the persisted highest timestamp (a restart fences there)
        self.top = -1  # the highest timestamp accepted
        self.restart_fence = -1
        #: Why the restart fence is where it is: ``lease`` (the previous run), ``high`` (a
        #: timestamp accepted ahead of the clock) or ``lost`` (a new or lost state).
        self.fence_cause = ""
        self.dirty: dict[str, int] = {}
        self._claim: tuple[int, int, str] = (-1, -1, "")

    @property
    def high_key(self) -> str:
        return f"{self.prefix}:high"

    @property
    def lease_key(self) -> str:
        return f"{self.prefix}:lease"

    @property
    def ahead_key(self) -> str:
        """The previous version's margin (read once, migrated to :attr:`high_key`)."""
        return f"{self.prefix}:ahead"

    def store_key(self, key: tuple[int, int, int]) -> str:
        return f"{self.prefix}:{key[0]}:{key[1]}:{key[2]}"

    # --- check: records nothing --------------------------------------------------------------

    def check(self, frame: Frame, now: int) -> None:
        """Direction, allow-list and every stream rule a replay fails (module docstring)."""
        if frame.sysid in self.refused_sources:
            raise WrongDirectionError(
                f"wrong link: system {frame.sysid} sends from the other side of the link"
            )
        if not frame.signed:
            if frame.msgid not in self.allow_unsigned:
                raise SignatureRequiredError(f"unsigned message {frame.msgid} not allow-listed")
            if frame.version == 1 and frame.msgid not in self.allow_v1:
                raise SignatureRequiredError(f"MAVLink v1 message {frame.msgid} not allow-listed")
            return
        stream = self._judge(frame.stream, frame.timestamp, now)
        if stream is None and not self.stored and frame.timestamp < now - self.new_stream_max_age:
            raise MessageStaleError(self._too_old(frame.timestamp, now))

    def admit(self, frame: Frame, *, trusted: bool, own_link_id: int) -> FrameAdmission:
        """A trusted link's unsigned v2 frame is signed on its behalf; a frame from an
        untrusted link carrying ``own_link_id`` (the link id the router signs with) is
        ``WRONG_DIRECTION``: the router signed it for a link whose key has no guard
        committing it, so a copy reflected back must not count as a new stream."""
        if trusted:
            unsigned_v2 = frame.version == 2 and not frame.signed
            return FrameAdmission.SIGN if unsigned_v2 else FrameAdmission.JUDGE
        if frame.signed and frame.link_id == own_link_id:
            raise WrongDirectionError(
                f"wrong link: a frame this router signed (link id {own_link_id}) "
                "came back from a ground link"
            )
        return FrameAdmission.JUDGE

    def bind(self, frame: Frame) -> None:
        """``WRONG_TARGET`` for a frame addressed to another vehicle than ``system_id``."""
        if self.system_id is None:
            return
        target = target_system(frame)
        if target not in (None, 0, self.system_id):
            raise WrongTargetError(f"frame addressed to system {target}, not this vehicle")

    def bind_direction(self, frame: Frame) -> None:
        """The other side authenticated ``frame``: its source system is refused here from
        now on.  An unsigned frame teaches nothing (a spoofed allow-listed heartbeat must
        not silence the real sender)."""
        if frame.signed:
            self.refused_sources.add(frame.sysid)

    # --- commit ------------------------------------------------------------------------------

    def commit(self, frame: Frame, now: int, facts: Facts | None = None) -> Persist | None:
        """Judge again and commit an authenticated signed frame in memory (``None``), or say
        what must be read or persisted first (module docstring)."""
        key, ts = frame.stream, frame.timestamp
        if self.periodic and not self.generation:
            return Persist(claim=True)  # no start(): the first frame claims the lease
        stream = self._judge(key, ts, now)
        if stream is None:
            stored = None
            if self.stored:
                store_key = self.store_key(key)
                if facts is None or store_key not in facts.stored:
                    return Persist(lookup=store_key)
                stored = facts.stored[store_key]
            stream = self._open_stream(ts, now, stored)
        if self.periodic:
            if now > self.lease:
                return Persist(renew=True)
            if ts > max(self.lease, self.saved_high):
                return Persist(high=-(-ts // HIGH_STEP) * HIGH_STEP)
            self.top = max(self.top, ts)
        elif self.stored:
            if facts is None or facts.through is None:
                return Persist(through=(self.store_key(key), ts))
            if not facts.through:
                # Another guard on the same store (a second router, a restarted one still
                # running) already took this timestamp or a later one: this copy is a replay.
                raise CounterReplayedError("timestamp already committed to the shared stream state")
        self.streams.commit(key, ts, lambda: stream)
        if stream.window is not None:
            stream.window.commit(ts)
        if self.periodic:
            self.dirty[self.store_key(key)] = self._mark(key)
        return None

    def _mark(self, key: tuple[int, int, int]) -> int:
        last = self.streams.mark(key)
        assert last is not None
        return last

    def high_persisted(self, high: int) -> None:
        """The driver made ``high`` durable under :attr:`high_key`."""
        if high > self.saved_high:
            self.saved_high = high
            self.counts["high_raises"] += 1

    @staticmethod
    def migration(found: int | None, high: int | None, ahead: int | None) -> int | None:
        """The highest timestamp to write under :attr:`high_key` before claiming, converted
        from the previous version's ``ahead`` margin: that version's fence, the expiry of
        the lease ``found`` (the one it wrote) plus the margin.  None once ``high`` exists:
        the driver writes ``high`` first, so a lease newer than the margin's never meets an
        absent ``high``, and a retry after a crash or a failed write converts the same."""
        if high is not None or ahead is None:
            return None
        generation, until = lease_parts(found or 0)
        return (until if generation else 0) + ahead

    def take_dirty(self) -> dict[str, int]:
        """The streams' high-water marks that moved since the last flush (now the driver's)."""
        dirty, self.dirty = self.dirty, {}
        return dirty

    def restore_dirty(self, dirty: dict[str, int]) -> None:
        """A flush failed: its marks are dirty again (the newer of each)."""
        for key, value in dirty.items():
            self.dirty[key] = max(value, self.dirty.get(key, -1))

    # --- the lease ---------------------------------------------------------------------------

    def claim(self, found: int | None, high: int | None, lost: float, now: int) -> int:
        """The lease value that claims the state, from the stored lease, highest timestamp
        (after :meth:`migration`) and the store's loss time (``NEVER``: none);
        ``STATE_UNAVAILABLE`` while another holds it."""
        generation, until = lease_parts(found or 0)
        if generation % 2 and now <= until + self.lease_skew:
            raise StateUnavailableError(
                f"another guard holds the MAVLink state {self.prefix!r} on this store "
                f"for {(until + self.lease_skew - now) / UNITS_PER_S:.2f} s more"
            )
        fences = [(until if generation else -1, "lease"), (-1 if high is None else high, "high")]
        if lost != NEVER:  # a new process (memory), a lost file, a flushed Redis
            fences.append((int((lost - MAV_EPOCH) * UNITS_PER_S) + self.max_forward, "lost"))
        fence, cause = max(fences, key=lambda f: (f[0], _CAUSES.index(f[1])))
        self._claim = (fence, -1 if high is None else high, cause if fence >= 0 else "")
        return lease_value(generation + (1 if generation % 2 == 0 else 2), now + self.lease_len)

    def claimed(self, value: int, written: bool) -> None:
        """The driver wrote the claim ``value`` (``written``: the store advanced to it)."""
        if not written:
            raise StateUnavailableError(f"another guard claimed {self.prefix!r} at once")
        fence, high, cause = self._claim
        self.generation = lease_parts(value)[0]
        self.saved_high = max(self.saved_high, high)
        self.lease = max(self.lease, lease_parts(value)[1])
        if fence > self.restart_fence:
            self.restart_fence, self.fence_cause = fence, cause
        self.counts["lease_claims"] += 1

    def renewal(self, now: int) -> int:
        """The lease value extending the held lease to ``now + lease_len``."""
        if not self.generation:
            raise StateUnavailableError(f"this guard no longer holds {self.prefix!r}")
        return lease_value(self.generation, now + self.lease_len)

    def renewed(self, value: int, written: bool, found: int | None) -> None:
        """The renewal ``value`` was written (or not: ``found`` is the stored lease then);
        a lease another guard took over fails closed."""
        generation, until = lease_parts(value)
        if written:
            if generation == self.generation:
                self.lease = max(self.lease, until)
            return
        if lease_parts(found or 0)[0] != generation:
            self.generation, self.lease = 0, -1
            self.counts["lease_lost"] += 1
            raise StateUnavailableError(f"another guard took over {self.prefix!r}")

    def release(self, now: int) -> int | None:
        """Give the lease up (clean stop): the value to write, None if none is held.  The
        expiry written is the stop time or the highest timestamp accepted, the later, so the
        restart fence starts there."""
        if not self.generation:
            return None
        released = self.generation + 1
        self.generation, self.lease = 0, -1
        return lease_value(released, max(now, self.top))

    # --- the stream rules --------------------------------------------------------------------

    def _judge(self, key: tuple[int, int, int], ts: int, now: int) -> _Stream | None:
        """Records nothing: the rules a held stream's timestamp, or a new stream's, must
        pass; the stream's entry, or None for a stream the table does not hold."""
        if ts > now + self.max_forward:
            raise MessageFromFutureError(
                f"timestamp {_s(ts - now)} s ahead of the receiver's clock "
                f"(limit {_s(self.max_forward)} s)"
            )
        if ts <= self.restart_fence:
            why = "the previous run may have accepted it"
            if self.fence_cause == "high" and self.restart_fence > now:  # a clock spike's
                why = (
                    f"the previous run accepted a frame stamped {_s(self.restart_fence - now)} s"
                    " ahead of this clock"
                )
            fenced = RestartFenceError(
                f"old timestamp: {_s(self.restart_fence - ts)} s below the restart fence ({why})"
            )
            fenced.below_s = (self.restart_fence - ts) / UNITS_PER_S
            raise fenced
        stream = self.streams.check(key, ts)
        if stream is None:
            return None
        last = self._mark(key)
        if ts <= stream.floor:
            raise CounterReplayedError(
                f"old timestamp: {_s(stream.floor - ts)} s behind the persisted stream state"
            )
        if stream.window is None:
            if ts <= last:
                raise CounterReplayedError(
                    f"old timestamp: {_s(last - ts)} s behind the stream's last"
                )
        else:
            stream.window.check(ts)
        return stream

    def _open_stream(self, ts: int, now: int, stored: int | None) -> _Stream:
        """A stream the table does not hold: its persisted high-water (if any) becomes its
        floor; without one, its first timestamp must be recent.  The table's eviction
        fence applies either way (a stream evicted before its last flush may have a
        persisted value below what this process accepted)."""
        if stored is None and ts < now - self.new_stream_max_age:
            raise MessageStaleError(self._too_old(ts, now))
        stream = _Stream(floor=-1 if stored is None else stored)
        if ts <= stream.floor:
            raise CounterReplayedError(
                f"old timestamp: {_s(stream.floor - ts)} s behind the persisted stream state"
            )
        if self.reorder_window:
            stream.window = CounterWindow(self.reorder_window, limit=TS_LIMIT)
        return stream

    def _too_old(self, ts: int, now: int) -> str:
        return (
            f"old timestamp: new stream {_s(now - ts)} s behind the receiver's clock "
            f"(limit {_s(self.new_stream_max_age)} s)"
        )


def _s(units: int) -> str:
    """MAVLink units as seconds, for a refusal's reason (the gap an operator asks about)."""
    return f"{units / UNITS_PER_S:.2f}"
