"""MAVLink v2 signing guard: verify, bind to this vehicle, timestamp rules, commit.

Two phases, as everywhere: :meth:`MavlinkGuard.check` records nothing, :meth:`MavlinkGuard.open`
checks, authenticates, commits.  A frame is judged in this order: strict **parse**
(:mod:`~antireplay.mavlink.codec`) -> ``INVALID_FRAME``; **direction**: a source system of the
other side (the vehicle's ``system_id``, any id authenticated the other way) ->
``WRONG_DIRECTION``, unsigned frames only if allow-listed -> ``SIGNATURE_REQUIRED``;
**timestamp rules** from memory only (ahead of ``max_forward_s``, at or below the restart fence,
not above the stream's last, below the table's eviction fence), so a replay costs no HMAC;
constant-time **verify** -> ``SIGNATURE_INVALID`` (nothing before it touches the stream table,
so a forged ``2**48 - 1`` jams nothing); **bind** ``target_system`` -> ``WRONG_TARGET``;
**commit** under a lock (rules again; a new stream starts above its persisted high-water or
within ``new_stream_max_age_s`` of the receiver's wall clock).  Streams live in a bounded
:class:`~antireplay.core.counters.FencedTable`.

Persistence: a lease and a restart fence, not an fsync per frame.  MAVLink timestamps are
wall-anchored, so the store keeps a **lease** (accepts only while ``now <= lease``, renewed
by a flusher every ``persist_interval_s``), ``ahead`` (the largest ``ts - now`` accepted,
written before accepting a frame that exceeds it) and each stream's high-water.  At start the
restart fence is ``previous lease expiry + ahead``: everything accepted before a stop or
``kill -9`` is refused; after a crash the guard waits for the old lease to expire.  A lost
store fences at the loss time plus ``max_forward_s``.  The lease is exclusive (odd/even
generations through ``advance``): a second guard on one prefix is ``STATE_UNAVAILABLE`` until
it takes over; guards *active at once* use ``write_through=True`` (one store write per frame).
"""

from __future__ import annotations

import hashlib
import hmac
import threading
import time
from collections import Counter
from dataclasses import dataclass

from antireplay.core.clock import Clock, resolve
from antireplay.core.counters import CounterWindow, FencedTable
from antireplay.core.errors import (
    CounterReplayedError,
    MessageFromFutureError,
    MessageStaleError,
    ReplayAttackError,
    SignatureInvalidError,
    SignatureRequiredError,
    StateUnavailableError,
    WrongDirectionError,
    WrongTargetError,
)
from antireplay.core.messages import StrEnum
from antireplay.core.window import NEVER
from antireplay.mavlink.codec import (
    MAV_EPOCH,
    SIG_LEN,
    SIGNED,
    STX_V2,
    TS_LIMIT,
    UNITS_PER_S,
    Frame,
    mav_time,
    parse_frame,
    target_system,
)
from antireplay.state import ReplayStore

_MS = UNITS_PER_S // 1000  # the lease's expiry is stored in milliseconds
_GENERATION = 2**42  # lease value = generation * 2**42 + expiry (ms): 139 years of expiry
_AHEAD_STEP = UNITS_PER_S // 10  # the persisted ahead margin grows by 0.1 s steps


@dataclass(frozen=True, slots=True)
class MavVerdict:
    """An accepted frame."""

    stream: tuple[int, int, int]
    msgid: int
    timestamp: int
    signed: bool
    frame: Frame  # the parsed frame, so that an adapter routes without parsing it again


class Admission(StrEnum):
    """What a frame from a router's link needs before its guard judges it
    (:meth:`MavlinkGuard.admit`)."""

    JUDGE = "judge"  # as it came
    SIGN = "sign"  # an unsigned v2 frame from a trusted tool: sign it on its behalf, then judge


@dataclass
class _Stream:
    """A stream's entry beside its high-water mark in the table (the mark is ``last``)."""

    floor: int = -1  # restored from a store: everything at or below was (or may have been) seen
    window: CounterWindow | None = None


class MavlinkGuard:
    """Judges MAVLink v2 frames: :meth:`check` records nothing, :meth:`open` checks,
    verifies, binds and commits (module docstring).

    With a store, call :meth:`start` before the first frame (it claims the lease and
    starts the flusher; a first frame claims lazily otherwise) and :meth:`stop` after
    the last (it flushes and releases).
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
        self.allow_unsigned = allow_unsigned
        self.allow_v1 = allow_v1 & allow_unsigned
        self.max_streams = max_streams
        self.reorder_window = reorder_window
        self.new_stream_max_age = int(new_stream_max_age_s * UNITS_PER_S)
        self.max_forward = int(max_forward_s * UNITS_PER_S)
        self.prefix = store_prefix
        self.write_through = write_through
        self.persist_interval_s = persist_interval_s
        self._lease_len = int(2 * persist_interval_s * UNITS_PER_S)
        self._lease_skew = int(lease_skew_s * UNITS_PER_S)
        #: Source system ids that belong to the other direction (module docstring).
        self.refused_sources: set[int] = set() if system_id is None else {system_id}
        self._streams: FencedTable[tuple[int, int, int], _Stream] = FencedTable(max_streams)
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        # Periodic persistence (module docstring): all MAVLink units except the generation.
        self._generation = 0  # odd while this guard holds the lease, 0 when it does not
        self._lease = -1  # frames are accepted only while now <= _lease
        self._ahead = 0  # the persisted largest ts - now
        self._high = -1  # the largest receiver time at which a frame was accepted
        self.restart_fence = -1
        self._dirty: dict[str, int] = {}
        self._lease_lock = threading.Lock()
        self._stopping = threading.Event()
        self._flusher: threading.Thread | None = None

    def __len__(self) -> int:
        return len(self._streams)

    @property
    def periodic(self) -> bool:
        """Whether this guard persists periodically behind a lease (module docstring)."""
        return self.store is not None and not self.write_through

    def check(self, raw: bytes) -> Frame:
        """Records nothing: parse, direction, allow-list and every stream rule a replay
        fails, before any cryptography (steps 1 to 3 of the module docstring)."""
        frame = parse_frame(raw)
        if frame.sysid in self.refused_sources:
            raise WrongDirectionError(
                f"wrong link: system {frame.sysid} sends from the other side of the link"
            )
        if not frame.signed:
            if frame.msgid not in self.allow_unsigned:
                raise SignatureRequiredError(f"unsigned message {frame.msgid} not allow-listed")
            if frame.version == 1 and frame.msgid not in self.allow_v1:
                raise SignatureRequiredError(f"MAVLink v1 message {frame.msgid} not allow-listed")
            return frame
        now = mav_time(self.clock)
        stream = self._judge(frame.stream, frame.timestamp, now)
        if (
            stream is None
            and self.store is None
            and frame.timestamp < now - self.new_stream_max_age
        ):
            raise MessageStaleError(self._too_old(frame.timestamp, now))
        return frame

    def admit(self, raw: bytes, *, trusted: bool, own_link_id: int) -> Admission:
        """Records nothing: what a frame a router received for this guard needs before
        :meth:`open`.  A trusted link's unsigned v2 frame is signed on its behalf; a frame
        from an untrusted link carrying ``own_link_id`` (the link id the router signs with)
        is ``WRONG_DIRECTION``: the router signed it for a link whose key has no guard
        committing it, so a copy reflected back must not count as a new stream."""
        signed_v2 = len(raw) > SIG_LEN and raw[0] == STX_V2 and bool(raw[2] & SIGNED)
        if trusted:
            unsigned_v2 = raw[:1] == bytes([STX_V2]) and not signed_v2
            return Admission.SIGN if unsigned_v2 else Admission.JUDGE
        if signed_v2 and raw[-SIG_LEN] == own_link_id:
            raise WrongDirectionError(
                f"wrong link: a frame this router signed (link id {own_link_id}) "
                "came back from a ground link"
            )
        return Admission.JUDGE

    def bind_direction(self, verdict: MavVerdict) -> None:
        """The other side of the link authenticated ``verdict``: its source system belongs
        there and is refused here from now on (*Direction binding*).  An unsigned frame
        teaches nothing: a spoofed allow-listed heartbeat must not silence the real sender."""
        if verdict.signed:
            self.refused_sources.add(verdict.frame.sysid)

    def open(self, raw: bytes) -> MavVerdict:
        """Check, verify the signature, bind, commit: accept one frame or raise a typed
        :class:`ReplayAttackError`.  Of two racers on one timestamp exactly one passes."""
        frame = self.check(raw)
        if not frame.signed:
            self._bind(frame)
            return MavVerdict(frame.stream, frame.msgid, 0, False, frame)
        expected = hashlib.sha256(self._key + raw[:-6]).digest()[:6]
        if not hmac.compare_digest(expected, raw[-6:]):
            raise SignatureInvalidError("MAVLink signature does not verify")
        self._bind(frame)
        with self._lock:
            self._commit(frame, mav_time(self.clock))
        return MavVerdict(frame.stream, frame.msgid, frame.timestamp, True, frame)

    # --- lifecycle: lease, flusher ---------------------------------------------------------

    def start(self, wait_s: float | None = None) -> None:
        """Claim the lease (waiting up to ``wait_s``, by default one lease, for a crashed
        owner's lease to expire) and start the flusher.  No-op without periodic persistence."""
        if not self.periodic:
            return
        budget = (
            (self._lease_len + self._lease_skew) / UNITS_PER_S + 1 if wait_s is None else wait_s
        )
        deadline = time.monotonic() + budget
        while True:
            try:
                with self._lock:
                    if not self._generation:
                        self._acquire(mav_time(self.clock))
                break
            except StateUnavailableError:
                if time.monotonic() >= deadline:
                    raise
                time.sleep(0.05)  # a crashed owner's lease runs out on the wall clock
        if self._flusher is None:
            self._stopping.clear()
            self._flusher = threading.Thread(target=self._flush_loop, daemon=True)
            self._flusher.start()

    def stop(self) -> None:
        """Stop the flusher, persist what is dirty and release the lease (clean stop)."""
        if self._flusher is not None:
            self._stopping.set()
            self._flusher.join()
            self._flusher = None
        if not self.periodic:
            return
        self.flush()
        with self._lock, self._lease_lock:
            if self._generation:
                released = self._generation + 1
                until = max(mav_time(self.clock), self._high)
                self._generation, self._lease = 0, -1
                self._write_lease(released, until)

    def flush(self) -> None:
        """Persist the streams that moved and renew the lease (the flusher calls this)."""
        if not self.periodic:
            return
        with self._lock:
            dirty, self._dirty = self._dirty, {}
        store = self._persistent_store()
        try:
            for key, value in dirty.items():
                store.advance(key, value)
        except BaseException:
            with self._lock:
                for key, value in dirty.items():
                    self._dirty[key] = max(value, self._dirty.get(key, -1))
            raise
        self.counts["flushes"] += 1
        if self._generation:
            self._renew(mav_time(self.clock))

    def _flush_loop(self) -> None:
        while not self._stopping.wait(self.persist_interval_s):
            try:
                self.flush()
            except ReplayAttackError:  # store down, lease lost: the frame path fails closed
                self.counts["persist_failures"] += 1

    def _persistent_store(self) -> ReplayStore:
        if self.store is None:
            raise StateUnavailableError("no store configured")
        return self.store

    def _acquire(self, now: int) -> None:
        """Claim the lease and raise the restart fence (caller holds ``_lock``)."""
        store = self._persistent_store()
        with self._lease_lock:
            found = store.current(self._lease_key)
            generation, until = divmod(found or 0, _GENERATION)
            until *= _MS
            if generation % 2 and now <= until + self._lease_skew:
                raise StateUnavailableError(
                    f"another guard holds the MAVLink state {self.prefix!r} on this store "
                    f"for {(until + self._lease_skew - now) / UNITS_PER_S:.2f} s more"
                )
            ahead = store.current(self._ahead_key) or 0
            fence = until + ahead if generation else -1
            lost = store.verify().fence  # a new process (memory), a lost file, a flushed Redis
            if lost != NEVER:
                fence = max(fence, int((lost - MAV_EPOCH) * UNITS_PER_S) + self.max_forward)
            claimed = generation + (1 if generation % 2 == 0 else 2)
            if not self._write_lease(claimed, now + self._lease_len):
                raise StateUnavailableError(f"another guard claimed {self.prefix!r} at once")
            self._generation, self._ahead = claimed, ahead
            self.restart_fence = max(self.restart_fence, fence)
            self.counts["lease_claims"] += 1

    def _renew(self, now: int) -> None:
        """Extend the lease to ``now + 2 intervals``; losing it to another guard fails closed."""
        with self._lease_lock:
            generation = self._generation
            if not generation:
                raise StateUnavailableError(f"this guard no longer holds {self.prefix!r}")
            if self._write_lease(generation, now + self._lease_len):
                return
            found = self._persistent_store().current(self._lease_key) or 0
            if found // _GENERATION != generation:
                self._generation, self._lease = 0, -1
                self.counts["lease_lost"] += 1
                raise StateUnavailableError(f"another guard took over {self.prefix!r}")

    def _write_lease(self, generation: int, until: int) -> bool:
        """``advance`` the lease key (caller holds ``_lease_lock``); remember it if ours."""
        until_ms = -(-until // _MS)
        if not self._persistent_store().advance(
            self._lease_key, generation * _GENERATION + until_ms
        ):
            return False
        if generation % 2:
            self._lease = max(self._lease, until_ms * _MS)
        return True

    @property
    def _lease_key(self) -> str:
        return f"{self.prefix}:lease"

    @property
    def _ahead_key(self) -> str:
        return f"{self.prefix}:ahead"

    # --- the frame path --------------------------------------------------------------------

    def _bind(self, frame: Frame) -> None:
        if self.system_id is None:
            return
        target = target_system(frame)
        if target not in (None, 0, self.system_id):
            raise WrongTargetError(f"frame addressed to system {target}, not this vehicle")

    def _judge(self, key: tuple[int, int, int], ts: int, now: int) -> _Stream | None:
        """Records nothing: the rules a held stream's timestamp, or a new stream's, must
        pass; the stream's entry, or None for a stream the table does not hold."""
        if ts > now + self.max_forward:
            raise MessageFromFutureError(
                f"timestamp {_s(ts - now)} s ahead of the receiver's clock "
                f"(limit {_s(self.max_forward)} s)"
            )
        if ts <= self.restart_fence:
            raise MessageStaleError(
                f"old timestamp: {_s(self.restart_fence - ts)} s below the restart fence "
                "(the previous run may have accepted it)"
            )
        stream = self._streams.check(key, ts)
        if stream is None:
            return None
        last = self._streams.mark(key)
        assert last is not None
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

    def _too_old(self, ts: int, now: int) -> str:
        return (
            f"old timestamp: new stream {_s(now - ts)} s behind the receiver's clock "
            f"(limit {_s(self.new_stream_max_age)} s)"
        )

    def _commit(self, frame: Frame, now: int) -> None:
        key, ts = frame.stream, frame.timestamp
        periodic = self.periodic
        if periodic and not self._generation:
            self._acquire(now)  # no start(): the first frame claims the lease
        stream = self._judge(key, ts, now)
        if stream is None:
            stream = self._open_stream(key, ts, now)
        if periodic:
            self._before_accept(ts, now)
        elif self.store is not None and not self.store.advance(self._store_key(key), ts):
            # Another guard on the same store (a second router, a restarted one still
            # running) already took this timestamp or a later one: this copy is a replay.
            raise CounterReplayedError("timestamp already committed to the shared stream state")
        self._streams.commit(key, ts, lambda: stream)
        if stream.window is not None:
            stream.window.commit(ts)
        if periodic:
            last = self._streams.mark(key)
            assert last is not None
            self._dirty[self._store_key(key)] = last

    def _before_accept(self, ts: int, now: int) -> None:
        """What must be durable before a frame is accepted: a live lease, the ahead margin."""
        if now > self._lease:
            self.counts["frame_path_renewals"] += 1
            self._renew(now)
        ahead = ts - now
        if ahead > self._ahead:
            margin = -(-ahead // _AHEAD_STEP) * _AHEAD_STEP
            self._persistent_store().advance(self._ahead_key, margin)
            self._ahead = margin
            self.counts["ahead_raises"] += 1
        self._high = max(self._high, now)

    def _open_stream(self, key: tuple[int, int, int], ts: int, now: int) -> _Stream:
        """A stream the table does not hold: its persisted high-water (if any) becomes its
        floor; without one, its first timestamp must be recent.  The table's eviction
        fence applies either way (a stream evicted before its last flush may have a
        persisted value below what this process accepted)."""
        stored = self.store.current(self._store_key(key)) if self.store is not None else None
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

    def _store_key(self, key: tuple[int, int, int]) -> str:
        return f"{self.prefix}:{key[0]}:{key[1]}:{key[2]}"


def _s(units: int) -> str:
    """MAVLink units as seconds, for a refusal's reason (the gap an operator asks about)."""
    return f"{units / UNITS_PER_S:.2f}"
