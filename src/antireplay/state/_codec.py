"""Stored values decoded in one place: counters, floats, integers and ids, strictly.

Counters are fixed-width decimal strings: 64-bit safe and ordered as text.  A
stored value that is not what its slot holds (written by hand, by another program,
or torn) is answered with a :class:`~antireplay.core.errors.StateFileError` naming
the store, the key and the recovery, never a bare ``ValueError``/``TypeError``, and
never a guess at what was meant (no NaN, no ``inf``, no hex, no blob read as text).
At start that error refuses the start; on the serving path a store answers it as
:func:`serving` (``STATE_UNAVAILABLE``, 503), still naming the recovery.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from typing import TypeVar

from antireplay.core.errors import StateFileError, StateUnavailableError

T = TypeVar("T")
WIDTH = 20  # 2**64 has 20 digits
_FLOAT = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")


def encode(value: int) -> str:
    if not 0 <= value < 10**WIDTH:
        raise ValueError(f"counter {value} out of range")
    return str(value).zfill(WIDTH)


def undecodable(
    value: object, expected: str, *, where: str, key: str, recovery: str
) -> StateFileError:
    """The error for ``value`` stored under ``key`` (as shown) in ``where`` (the file or
    URL), which is not ``expected``."""
    shown = repr(value)
    shown = shown if len(shown) <= 40 else shown[:40] + "..."
    return StateFileError(where, f"{key} holds {shown}, not {expected}", recovery=recovery)


def decode(text: str | bytes, *, where: str, key: str, recovery: str) -> int:
    """The counter ``text`` holds; ``where`` (the file or URL), ``key`` and ``recovery``
    name the undecodable value in the error."""
    raw = text.decode("ascii", "replace") if isinstance(text, bytes) else text
    if len(raw) != WIDTH or not (raw.isascii() and raw.isdigit()):
        expected = f"a {WIDTH}-digit counter"
        raise undecodable(raw, expected, where=where, key=f"counter {key!r}", recovery=recovery)
    return int(raw)


def decode_float(value: object, *, where: str, key: str, recovery: str) -> float:
    """A stored time (expiry, fence, watermark): a number, never NaN; as text (Redis's
    values) only a plain decimal; a blob never."""
    if isinstance(value, str) and _FLOAT.fullmatch(value):
        return float(value)
    if isinstance(value, (int, float)) and not isinstance(value, bool) and not math.isnan(value):
        return float(value)
    raise undecodable(value, "a number", where=where, key=key, recovery=recovery)


def decode_int(value: object, *, where: str, key: str, recovery: str) -> int:
    """A stored non-negative count (a generation, data-loss events); a blob never."""
    if isinstance(value, str) and value.isascii() and value.isdigit():
        return int(value)
    if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        return value
    raise undecodable(value, "a non-negative integer", where=where, key=key, recovery=recovery)


def decode_hex(value: object, digits: int, *, where: str, key: str, recovery: str) -> str:
    """A stored id of ``digits`` lowercase hex digits (a deployment id)."""
    if isinstance(value, str) and re.fullmatch(f"[0-9a-f]{{{digits}}}", value):
        return value
    expected = f"{digits} hex digits"
    raise undecodable(value, expected, where=where, key=key, recovery=recovery)


def serving(op: Callable[[], T]) -> T:
    """``op`` on the serving path (a lookup, a commit, a readiness probe): stored data that
    does not decode is 503 (a fresh ESTOP still passes), naming the store and the recovery
    without claiming that a start is refused."""
    try:
        return op()
    except StateFileError as exc:
        reason = f"{exc.what} {exc.path}: {exc.problem}. Recover with: {exc.recovery}"
        raise StateUnavailableError(reason) from None
