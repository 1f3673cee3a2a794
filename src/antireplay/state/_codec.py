"""Counter values as fixed-width decimal strings: 64-bit safe and ordered as text.

A stored value that is not such a string (written by hand, by another program, or
torn) is not a counter at all: :func:`decode` answers it with a
:class:`~antireplay.core.errors.StateFileError` naming the store and the recovery, never a
bare ``ValueError``, and never a guess at what was meant.
"""

from __future__ import annotations

from antireplay.core.errors import StateFileError

WIDTH = 20  # 2**64 has 20 digits


def encode(value: int) -> str:
    if not 0 <= value < 10**WIDTH:
        raise ValueError(f"counter {value} out of range")
    return str(value).zfill(WIDTH)


def decode(text: str | bytes, *, where: str, key: str, recovery: str) -> int:
    """The counter ``text`` holds; ``where`` (the file or URL), ``key`` and ``recovery``
    name the undecodable value in the error."""
    raw = text.decode("ascii", "replace") if isinstance(text, bytes) else text
    if len(raw) != WIDTH or not (raw.isascii() and raw.isdigit()):
        shown = raw if len(raw) <= 40 else raw[:40] + "..."
        problem = f"counter {key!r} holds {shown!r}, not a {WIDTH}-digit counter"
        raise StateFileError(where, problem, recovery=recovery)
    return int(raw)
