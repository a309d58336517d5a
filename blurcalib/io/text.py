"""Counts in user-facing text: "1 frame", "2 frames"."""

from __future__ import annotations

__all__ = ["count"]


def count(n: int, noun: str, plural: str | None = None) -> str:
    """``n`` followed by ``noun`` in the number it takes.

    ``count(1, "frame")`` is ``"1 frame"``, ``count(34, "grid cell")`` ``"34 grid cells"``;
    ``plural`` gives an irregular plural.
    """
    return f"{n} {noun if n == 1 else plural or noun + 's'}"
