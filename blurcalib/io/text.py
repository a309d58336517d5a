"""User-facing text: counts ("1 frame", "2 frames") and file names written as UTF-8."""

from __future__ import annotations

import os

__all__ = ["count", "printable_name"]


def count(n: int, noun: str, plural: str | None = None) -> str:
    """``n`` followed by ``noun`` in the number it takes.

    ``count(1, "frame")`` is ``"1 frame"``, ``count(34, "grid cell")`` ``"34 grid cells"``;
    ``plural`` gives an irregular plural.
    """
    return f"{n} {noun if n == 1 else plural or noun + 's'}"

def printable_name(name: str) -> str:
    """A file name as text that can be written as UTF-8: bytes of a name that is not valid
    UTF-8 (decoded by Python as surrogates) are written as ``\\xNN`` escapes (``caf\\xe9.png``)."""
    return os.fsencode(name).decode("utf-8", "backslashreplace")
