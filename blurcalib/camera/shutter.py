"""When each sensor row is exposed: the global and the rolling shutter.

A rolling shutter exposes the rows of an ``H``-row sensor one after another. With the readout
ratio ``r = readout time / exposure time``, row ``v`` (px, 0 at the top) is exposed over the
window of unit length (one exposure time) centred at

    c(v) = r (v - (H - 1) / 2) / H        (exposure times; c = 0 at the middle row)

so the frame's reference instant ``tau = 0`` is the middle row's mid-exposure. ``r = 0`` is the
global shutter: every row is exposed over ``[-1/2, 1/2]``.

A renderer integrates the motion by samples on one time grid shared by all rows
(:func:`exposure_grid`): sample ``j`` stands for the interval ``[a_j, a_j + 1/T]`` and row ``v``
weighs it by the interval's overlap with its window, so each row's weights sum to 1 and their
mean time is exactly ``c(v)``. With ``r = 0`` the grid is the ``T`` samples
``tau_i = (i + 1/2) / T - 1/2`` of the global shutter, each of weight ``1/T``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["ExposureGrid", "exposure_grid", "row_time", "window_weights"]


def row_time(v: ArrayLike, height: int, ratio: float) -> np.ndarray:
    """``c(v) = r (v - (H - 1) / 2) / H`` exposure times: the centre of row ``v``'s window
    (``v`` px, continuous; ``(N,)`` -> ``(N,)``; 0 for the global shutter, ``r = 0``)."""
    v = np.asarray(v, dtype=np.float64)
    if ratio == 0:
        return np.zeros_like(v)
    return ratio * (v - (height - 1) / 2.0) / height


@dataclass(frozen=True)
class ExposureGrid:
    """Time samples shared by every row of a frame.

    Attributes:
        times: ``(N,)`` sample times (exposure times), the centres of the intervals.
        start: the first interval's start; every interval is ``1 / samples`` long.
        samples: ``T``, samples per exposure time.
    """

    times: np.ndarray
    start: float
    samples: int


def exposure_grid(height: int, ratio: float, samples: int) -> ExposureGrid:
    """The grid covering every row's window: from ``c(0) - 1/2`` to ``c(H - 1) + 1/2`` in steps
    of ``1 / samples``."""
    first = float(row_time(0.0, height, ratio)) - 0.5
    span = 2.0 * (float(row_time(height - 1.0, height, ratio)) + 0.5)
    count = max(samples, math.ceil(span * samples - 1e-9))
    return ExposureGrid(first + (np.arange(count) + 0.5) / samples, first, samples)


def window_weights(grid: ExposureGrid, centres: ArrayLike) -> np.ndarray:
    """``(N, M)`` weights of the grid's samples for windows centred at ``centres (M,)``: the
    overlap of sample ``j``'s interval with ``[c - 1/2, c + 1/2]`` (each column sums to 1)."""
    c = np.asarray(centres, dtype=np.float64)[None, :]
    a = grid.start + np.arange(len(grid.times))[:, None] / grid.samples
    b = a + 1.0 / grid.samples
    return cast(np.ndarray, np.clip(np.minimum(b, c + 0.5) - np.maximum(a, c - 0.5), 0.0, None))
