"""Counter values as fixed-width decimal strings: 64-bit safe and ordered as text."""

from __future__ import annotations

WIDTH = 20  # 2**64 has 20 digits


def encode(value: int) -> str:
    if not 0 <= value < 10**WIDTH:
        raise ValueError(f"counter {value} out of range")
    return str(value).zfill(WIDTH)


def decode(text: str | bytes) -> int:
    return int(text)
