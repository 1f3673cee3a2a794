"""The freshness window and msg_id rules (RCAN §8.3 Replay Attack Prevention), as a pure policy.

Theory of operation
-------------------
Rule 1: everything that decides whether an RCAN message is fresh and unique lives
in this file, in :class:`Window`.  The policy takes values (the message's msg_id,
timestamp and type, the receiver's ``now``, and the :class:`Seen` state a store
read or wrote atomically for that msg_id) and returns a :class:`Verdict` or
a typed error (raised by :meth:`Window.plan` and :meth:`Window.judge`; returned
as a :class:`Refusal` value by :meth:`Window.plan_or_refusal` and
:meth:`Window.decide`, the hot path's form: a refusal is an answer, and building
and raising an exception through compiled frames costs more than an admission).
It never reads a clock, sleeps, locks or does I/O; the one atomic store
operation is performed by the caller
(:class:`~antireplay.state.replay.ReplayCache`, the pipeline), between
:meth:`Window.plan` and :meth:`Window.judge`.

A message with timestamp ``ts`` (Unix seconds, the *sender's* clock) and window
``w`` is

* ``MESSAGE_STALE``        when ``now - ts > w``;
* ``MESSAGE_FROM_FUTURE``  when ``ts > now + skew``;
* ``MESSAGE_STALE`` (``detail="restart_fence"``) when ``ts <= fence + skew``:
  the store may have forgotten messages accepted before ``fence`` (a fresh
  process, a lost or rolled-back file, a Redis that restarted, failed over or
  was flushed), and such a message may have been one of them;
* ``MESSAGE_STALE`` (``detail="watermark"``) when its expiry ``ts + w`` is at or
  below the store's **watermark**, the largest expiry of any entry the store
  ever removed (expiry purge, saturation, a purge run on a clock that had
  stepped forward): such a message may have had its entry removed;
* ``MESSAGE_STALE`` (``detail="saturated"``) when the store is full and the
  message would not outlive the soonest-expiring entries (fail closed: a flood
  can make fresh messages be refused, never make a replay pass);
* ``REPLAY_DETECTED``      when its msg_id has an entry that has not expired.

``w`` is ``replay_window_s`` (default 30 s) and ``min(replay_window_s,
safety_window_s)`` (at most 10 s) for SAFETY messages (type 6).  An entry
*expires* at ``ts + w`` of the message that created it, on the receiver's wall
clock: exactly the instant after which the same message fails the freshness
test.  Entries are keyed on the sender's timestamp, never on receipt time.

The watermark is what makes a wall-clock step safe on every backend: a purge
that runs while the clock has stepped forward removes live entries and raises
the watermark to their expiry, so after the clock steps back every message
whose entry was removed early is refused.  In normal operation entries are
removed only after they expire, so the watermark stays below ``now`` and never
refuses a message the freshness test would accept.

ESTOP invariant: a fresh SAFETY message with ``safety_event == "ESTOP"`` is
always accepted; if its msg_id has a live entry, or it falls under the fence or
the watermark, or the store is saturated, the verdict carries
``warning="REPLAY_DETECTED"`` (to be audited), and the store records it anyway
(``force``), extending the entry of a later duplicate.  A stale ESTOP (older
than the safety window) is refused; STOP and RESUME get no exemption.  The
same exemption covers every failure of state or audit, as one rule,
:func:`estop_survives`: a store that cannot be reached
(:class:`~antireplay.state.replay.ReplayCache`, ``STATE_UNAVAILABLE``) or an audit
row that cannot be made durable (:mod:`antireplay.rcan.receive`,
``AUDIT_UNAVAILABLE``) refuses everything except a fresh, authentic ESTOP, which is
delivered flagged.

Timestamps are finite, non-negative Unix **seconds**: ``int``/``float`` or a
plain decimal string (``"1700000000.25"``, as the RCAN SDK emits).  Rejected
with ``INVALID_TIMESTAMP``: NaN, ±inf, booleans, ``None``, negatives, exponent
or signed strings, ISO-8601 strings, and values at or above 1e11 (milliseconds
sent in a seconds field; the SDK's ``timestamp_ms`` is converted by the
envelope layer, where its unit is explicit).

Two phases, one vocabulary: :meth:`Window.plan` validates and computes the
expiry (shape, staleness, future); the caller then either *checks* (a store
``lookup``, recording nothing) or *commits* (the store's atomic ``commit``),
and hands the resulting :class:`Seen` to :meth:`Window.judge`.

Speed: a normal install compiles this module with mypyc (``setup.py``;
:mod:`antireplay.core._native` picks the build), so it is written in the style that
compiles to native code: ``Final`` constants, plain classes with ``__slots__``,
plain ``if`` instead of generic builtins such as ``max``.
"""

from __future__ import annotations

import math
import re
from typing import Final, SupportsFloat, final

from antireplay.core.errors import (
    ConfigError,
    InvalidMessageIdError,
    InvalidTimestampError,
    MessageFromFutureError,
    MessageStaleError,
    ReplayAttackError,
    ReplayDetectedError,
)
from antireplay.core.messages import MessageType, SafetyEvent
from antireplay.core.settings import SecurityConfig

MAX_MSG_ID_LEN: Final = 128
#: Seconds values at or above this are treated as milliseconds sent by mistake (year 5138).
MILLISECONDS_THRESHOLD: Final = 1e11
#: "No entry", "nothing forgotten", "no fence": below every timestamp.
NEVER: Final = -math.inf

# Plain constants: enum attribute access costs ~150 ns on the hot path (CPython 3.11).
_SAFETY: Final = int(MessageType.SAFETY)
_ESTOP: Final = str(SafetyEvent.ESTOP)
_REPLAY: Final = "REPLAY_DETECTED"


def is_estop(msg_type: int, safety_event: str | None) -> bool:
    """The ESTOP invariant covers SAFETY messages with the ESTOP event only."""
    return msg_type == _SAFETY and safety_event == _ESTOP


def estop_survives(estop: bool, warning: str | None, failure: str) -> str | None:
    """Safety beats availability: the warning a fresh ESTOP (``Verdict.estop``) is
    delivered with despite ``failure`` (a state or audit outage's code), keeping a
    warning it already carries (one code per answer, the §8.3 flag first); ``None``:
    anything else fails closed."""
    if not estop:
        return None
    return failure if warning is None else warning


_DECIMAL = re.compile(r"[0-9]{1,12}(?:\.[0-9]{1,9})?")
_ISO_HINT = re.compile(r"[0-9]{4}-[0-9]{2}-[0-9]{2}")


@final
class Seen:
    """What a store holds for one msg_id, read (``lookup``) or written (``commit``) atomically.

    ``expiry`` is the entry's expiry (``NEVER`` if there is none); ``watermark`` and
    ``fence`` are the store's, as of the same atomic operation; ``recorded`` says that
    a commit wrote the entry; ``full`` that it could not, because the store is
    saturated; ``lost`` that this very operation found the store had lost state
    (and raised its fence).
    """

    __slots__ = ("expiry", "fence", "full", "lost", "recorded", "watermark")

    def __init__(  # noqa: PLR0917 - a value object, built positionally on the hot path
        self,
        expiry: float,
        watermark: float,
        fence: float,
        recorded: bool = False,
        full: bool = False,
        lost: bool = False,
    ) -> None:
        self.expiry: Final = expiry
        self.watermark: Final = watermark
        self.fence: Final = fence
        self.recorded: Final = recorded
        self.full: Final = full
        self.lost: Final = lost

    def __repr__(self) -> str:
        return (
            f"Seen(expiry={self.expiry!r}, watermark={self.watermark!r}, fence={self.fence!r}, "
            f"recorded={self.recorded!r}, full={self.full!r}, lost={self.lost!r})"
        )


@final
class Verdict:
    """A message the window admits: its timestamp, window, entry expiry and any warning.

    A plain class rather than a NamedTuple: the compiled build allocates it natively
    and its attributes are read-only.
    """

    __slots__ = ("estop", "expires_at", "msg_id", "timestamp", "warning", "window_s")

    def __init__(  # noqa: PLR0917 - a value object, built positionally on the hot path
        self,
        msg_id: str,
        timestamp: float,
        window_s: float,
        expires_at: float,
        warning: str | None = None,
        estop: bool = False,
    ) -> None:
        self.msg_id: Final = msg_id
        self.timestamp: Final = timestamp
        self.window_s: Final = window_s
        self.expires_at: Final = expires_at
        self.warning: Final = warning
        self.estop: Final = estop

    def __repr__(self) -> str:
        return (
            f"Verdict(msg_id={self.msg_id!r}, timestamp={self.timestamp!r}, "
            f"window_s={self.window_s!r}, expires_at={self.expires_at!r}, warning={self.warning!r})"
        )


@final
class Refusal:
    """A refusal as a value: the error's class, reason and detail (the hot path's answer,
    never raised itself: :meth:`error` builds the exception a raising caller raises).

    A plain value rather than the exception: building an exception costs more than a whole
    admission, and the refusals every replay meets are preallocated once.
    """

    __slots__ = ("count_key", "detail", "kind", "reason")

    def __init__(
        self, kind: type[ReplayAttackError], reason: str, detail: str | None = None
    ) -> None:
        self.kind: Final = kind
        self.reason: Final = reason
        self.detail: Final = detail
        #: What a refusal is counted under: the detail, else the code (a plain ``str``).
        self.count_key: Final[str] = detail if detail is not None else str(kind.code)

    @staticmethod
    def of(exc: ReplayAttackError) -> Refusal:
        """The refusal an error raised elsewhere (a malformed message, a store outage) is."""
        return Refusal(type(exc), exc.reason, exc.detail)

    @property
    def code(self) -> str:
        return str(self.kind.code)

    def error(self) -> ReplayAttackError:
        """The exception to raise for this refusal (a new one each time)."""
        return self.kind(self.reason, detail=self.detail)

    def __repr__(self) -> str:
        return f"Refusal({self.kind.__name__}, {self.reason!r}, detail={self.detail!r})"


_FENCED: Final = Refusal(
    MessageStaleError, "message may predate a loss or restart of the replay state", "restart_fence"
)
_UNDER_WATERMARK: Final = Refusal(
    MessageStaleError, "message is older than the replay state's low watermark", "watermark"
)
_SATURATED: Final = Refusal(
    MessageStaleError,
    "replay state saturated; message expires before every live entry",
    "saturated",
)
_REPLAYED: Final = Refusal(ReplayDetectedError, "msg_id already accepted within its window")


def coerce_timestamp(value: object) -> float:
    """Validate a timestamp and return it as float seconds, or raise ``INVALID_TIMESTAMP``."""
    if isinstance(value, bool) or value is None:
        raise InvalidTimestampError(f"timestamp must be Unix seconds, got {type(value).__name__}")
    if isinstance(value, int):
        if not 0 <= value < MILLISECONDS_THRESHOLD:
            raise InvalidTimestampError(
                "timestamp must be non-negative Unix seconds below 1e11 (not milliseconds)"
            )
        ts = float(value)
    elif isinstance(value, float):
        ts = value
    elif isinstance(value, str):
        if _DECIMAL.fullmatch(value) is None:
            hint = (
                " (ISO-8601 is not accepted; send Unix seconds)" if _ISO_HINT.match(value) else ""
            )
            raise InvalidTimestampError("timestamp string is not plain decimal seconds" + hint)
        ts = float(value)
    else:
        raise InvalidTimestampError(f"timestamp must be Unix seconds, got {type(value).__name__}")
    if not math.isfinite(ts):
        raise InvalidTimestampError("timestamp must be finite")
    if ts < 0:
        raise InvalidTimestampError("timestamp must not be negative")
    if ts >= MILLISECONDS_THRESHOLD:
        raise InvalidTimestampError(
            "timestamp looks like milliseconds; send seconds (or timestamp_ms in an envelope)"
        )
    return ts


def validate_msg_id(value: object) -> str:
    """A msg_id is a non-empty string of at most 128 characters."""
    if not isinstance(value, str):
        raise InvalidMessageIdError(f"msg_id must be a string, got {type(value).__name__}")
    if not value:
        raise InvalidMessageIdError("msg_id must not be empty")
    if len(value) > MAX_MSG_ID_LEN:
        raise InvalidMessageIdError(f"msg_id longer than {MAX_MSG_ID_LEN} characters")
    return value


@final
class Window:
    """The §8.3 rules as a pure policy: values in, verdict out (see the module docstring)."""

    __slots__ = ("safety_window_s", "skew_s", "window_s")

    def __init__(
        self,
        window_s: SupportsFloat = 30.0,
        skew_s: SupportsFloat = 5.0,
        safety_window_s: SupportsFloat = 10.0,
    ) -> None:
        # Protocol types on purpose: the compiled build checks them in _validated,
        # raising ConfigError (key, value, allowed range) instead of a bare TypeError.
        cfg = _validated(window_s, skew_s, safety_window_s)
        self.window_s: Final[float] = cfg.replay_window_s
        self.safety_window_s: Final[float] = min(cfg.safety_window_s, cfg.replay_window_s)
        self.skew_s: Final[float] = cfg.skew_s

    @classmethod
    def from_config(cls, config: SecurityConfig) -> Window:
        return cls(config.replay_window_s, config.skew_s, config.safety_window_s)

    def window_for(self, msg_type: int) -> float:
        """SAFETY messages get ``min(replay_window_s, safety_window_s)``; others the window."""
        return self.safety_window_s if msg_type == _SAFETY else self.window_s

    def plan(
        self, mid: object, ts: object, msg_type: int, event: str | None, now: float
    ) -> Verdict:
        """Shape, staleness and future checks; the expiry a commit would record."""
        planned = self.plan_or_refusal(mid, ts, msg_type, event, now)
        if isinstance(planned, Refusal):
            raise planned.error()
        return planned

    def plan_or_refusal(
        self, mid: object, ts: object, msg_type: int, event: str | None, now: float
    ) -> Verdict | Refusal:
        """:meth:`plan` with a stale or future message's refusal returned, not raised (a
        malformed msg_id or timestamp still raises: a hostile shape, never the hot path)."""
        if type(mid) is not str or not 0 < len(mid) <= MAX_MSG_ID_LEN:
            mid = validate_msg_id(mid)
        t = ts if type(ts) is float else coerce_timestamp(ts)
        if not 0.0 <= t < MILLISECONDS_THRESHOLD:
            t = coerce_timestamp(ts)  # raises INVALID_TIMESTAMP with the reason
        safety = msg_type == _SAFETY
        window = self.safety_window_s if safety else self.window_s
        if now - t > window:
            return Refusal(
                MessageStaleError, f"message is {now - t:.3f}s old; window is {window:g}s"
            )
        if t > now + self.skew_s:
            return Refusal(
                MessageFromFutureError,
                f"message is {t - now:.3f}s ahead; allowed skew is {self.skew_s:g}s",
            )
        return Verdict(mid, t, window, t + window, None, safety and event == _ESTOP)

    def judge(self, plan: Verdict, seen: Seen, now: float) -> Verdict:
        """The fence, watermark, saturation and duplicate rules on what the store holds."""
        verdict = self.decide(
            plan, seen.expiry, seen.watermark, seen.fence, seen.recorded, seen.full, now
        )
        if isinstance(verdict, Refusal):
            raise verdict.error()
        return verdict

    def decide(  # noqa: PLR0917 - the fields of a Seen, unboxed on the hot path
        self,
        plan: Verdict,
        expiry: float,
        watermark: float,
        fence: float,
        recorded: bool,
        full: bool,
        now: float,
    ) -> Verdict | Refusal:
        """:meth:`judge` on the fields of a :class:`Seen`, the refusal returned as a value
        (unraised): a refusal is an answer, not an exceptional path, and a caller that
        checks before recording passes its known ``watermark`` and ``fence`` without
        building a ``Seen``."""
        estop = plan.estop
        warning: str | None = None
        if plan.timestamp <= fence + self.skew_s:
            if not estop:
                return _FENCED
            warning = _REPLAY
        if plan.expires_at <= watermark:
            if not estop:
                return _UNDER_WATERMARK
            warning = _REPLAY
        if full and not estop:
            return _SATURATED
        if expiry >= now and not recorded:
            if not estop:
                return _REPLAYED
            warning = _REPLAY
        if warning is None:
            return plan
        return Verdict(plan.msg_id, plan.timestamp, plan.window_s, plan.expires_at, warning, estop)


def _validated(window_s: object, skew_s: object, safety_window_s: object) -> SecurityConfig:
    """Constructor arguments obey the same ranges as the YAML block (no clamping)."""
    seconds: dict[str, float] = {}
    for key, value in (
        ("replay_window_s", window_s),
        ("skew_s", skew_s),
        ("safety_window_s", safety_window_s),
    ):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(
                "window_s" if key == "replay_window_s" else key, value, "a number of seconds"
            )
        seconds[key] = float(value)
    return SecurityConfig.from_mapping(seconds)
