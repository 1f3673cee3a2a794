"""The operator-and-attacker demo: every §8.3 rule exercised against a real ReplayCache.

Each step states what the receiver must answer and what it did answer; the
demo fails (non-zero exit in the CLI) if any step differs.  Time is a
:class:`ManualClock`, so the demo is deterministic and instant.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from antireplay.clock import ManualClock
from antireplay.errors import ReplayAttackError
from antireplay.messages import MessageType, SafetyEvent
from antireplay.window import ReplayCache

ACCEPTED = "accepted"


@dataclass(frozen=True)
class StepResult:
    """One demo step: what the robot must answer and what it answered."""

    step: str
    expected: str
    got: str

    @property
    def ok(self) -> bool:
        return self.expected == self.got


def _answer(action: Callable[[], object]) -> str:
    try:
        verdict = action()
    except ReplayAttackError as exc:
        return f"{exc.code} ({exc.http_status})"
    warning = getattr(verdict, "warning", None)
    return ACCEPTED if warning is None else f"{ACCEPTED}, warning {warning}"


def run_window_demo() -> list[StepResult]:
    """Play the operator and the attacker against one receiver; return every step."""
    clock = ManualClock(wall=1_800_000_000.0)
    cache = ReplayCache(window_s=30, max_size=1_000, clock=clock)
    t0 = clock.wall()
    cmd, safety, estop = MessageType.COMMAND, MessageType.SAFETY, SafetyEvent.ESTOP
    steps: list[tuple[str, str, Callable[[], object]]] = [
        ("operator: move_forward", ACCEPTED, lambda: cache.check("cmd-1", t0, cmd)),
        ("attacker: exact replay", "REPLAY_DETECTED (409)", lambda: cache.check("cmd-1", t0, cmd)),
        ("attacker: 40 s old capture", "MESSAGE_STALE (408)", lambda: cache.check("old", t0 - 40)),
        (
            "attacker: stamped 60 s ahead",
            "MESSAGE_FROM_FUTURE (400)",
            lambda: cache.check("f", t0 + 60),
        ),
        ("attacker: timestamp 'nan'", "INVALID_TIMESTAMP (400)", lambda: cache.check("n", "nan")),
        ("operator: SAFETY STOP", ACCEPTED, lambda: cache.check("stop-1", t0, safety, "STOP")),
    ]
    results = [StepResult(name, want, _answer(act)) for name, want, act in steps]
    clock.advance(15)
    results.append(
        StepResult(
            "attacker: replay 15 s old command after a SAFETY msg",
            "REPLAY_DETECTED (409)",
            _answer(lambda: cache.check("cmd-1", t0, cmd)),
        )
    )
    now = clock.wall()
    flooded = ReplayCache(window_s=30, max_size=1_000, clock=clock)
    flooded.check("cmd-2", now, cmd)
    for i in range(5_000):
        try:
            flooded.check(f"flood-{i}", now + 5)
        except ReplayAttackError:
            break
    results.append(
        StepResult(
            f"attacker: 5000-id flood, then replay (cache holds {len(flooded)})",
            "MESSAGE_STALE (408)",
            _answer(lambda: flooded.check("cmd-2", now, cmd)),
        )
    )
    results += [
        StepResult(
            "operator: ESTOP", ACCEPTED, _answer(lambda: cache.check("e-1", now, safety, estop))
        ),
        StepResult(
            "network: duplicate fresh ESTOP",
            f"{ACCEPTED}, warning REPLAY_DETECTED",
            _answer(lambda: cache.check("e-1", now, safety, estop)),
        ),
        StepResult(
            "attacker: 11 s old ESTOP",
            "MESSAGE_STALE (408)",
            _answer(lambda: cache.check("e-old", now - 11, safety, estop)),
        ),
        StepResult(
            "operator: RESUME", ACCEPTED, _answer(lambda: cache.check("r-1", now, safety, "RESUME"))
        ),
        StepResult(
            "attacker: replay RESUME",
            "REPLAY_DETECTED (409)",
            _answer(lambda: cache.check("r-1", now, safety, "RESUME")),
        ),
    ]
    return results
