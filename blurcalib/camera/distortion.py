"""The distortion polynomial every parametric camera of :mod:`blurcalib.camera.lens` shares.

A model maps a viewing direction to a 2-D *base point* ``m = (x, y)`` (the perspective
``(X/Z, Y/Z)`` or the equidistant ``theta (X, Y) / rho``), distorts it and applies the focal
lengths and principal point. The distortion, with ``r^2 = x^2 + y^2``::

    radial = (1 + a1 r^2 + a2 r^4 + a3 r^6 + a4 r^8) / (1 + b1 r^2 + b2 r^4 + b3 r^6)
    d_x = x radial + 2 p1 x y + p2 (r^2 + 2 x^2) + s1 r^2
    d_y = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y + s3 r^2

holds each model as a choice of its 11 coefficients ``c = (a1, a2, a3, a4, b1, b2, b3, p1, p2,
s1, s3)`` (:data:`COEFFICIENTS`): OpenCV's Brown-Conrady ``(k1, k2, p1, p2, k3)`` and rational
model (``b`` = ``k4..k6``), the Kannala-Brandt ``theta_d`` polynomial (``a = k1..k4`` on the
equidistant base point) and the reference tool's thin-prism fisheye (``s1, s3`` = ``sx1, sy1``).

Arrays are float64: ``m (N, 2)``, Jacobians ``dd/dm (N, 2, 2)`` and ``dd/dc (N, 2, 11)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["COEFFICIENTS", "Distorted", "distort", "distort_with_jacobian", "radial_map", "radial_slope_root"]

COEFFICIENTS = ("a1", "a2", "a3", "a4", "b1", "b2", "b3", "p1", "p2", "s1", "s3")
"""The kernel's coefficients, in the order of its coefficient vector ``c (11,)``."""


@dataclass(frozen=True, eq=False)
class Distorted:
    """The distorted points and their derivatives.

    Attributes:
        d: ``(N, 2)`` distorted base points.
        d_m: ``(N, 2, 2)`` ``dd/dm`` (rows ``d_x, d_y``).
        d_c: ``(N, 2, 11)`` ``dd/dc`` in :data:`COEFFICIENTS` order.
    """

    d: np.ndarray
    d_m: np.ndarray
    d_c: np.ndarray


def _radial(r2: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``num, den`` of the radial factor and their derivatives ``d/d(r^2)``."""
    a1, a2, a3, a4, b1, b2, b3 = c[:7]
    num = 1.0 + r2 * (a1 + r2 * (a2 + r2 * (a3 + r2 * a4)))
    den = 1.0 + r2 * (b1 + r2 * (b2 + r2 * b3))
    dnum = a1 + r2 * (2.0 * a2 + r2 * (3.0 * a3 + r2 * 4.0 * a4))
    dden = b1 + r2 * (2.0 * b2 + r2 * 3.0 * b3)
    return num, den, dnum, dden


def _parts(m: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, ...]:
    """``x, y, r^2, 2 x y`` of base points ``m (N, 2)`` and :func:`_radial`'s four terms."""
    x, y = m[:, 0], m[:, 1]
    r2 = x * x + y * y
    return (x, y, r2, 2.0 * x * y, *_radial(r2, c))


def distort(m: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The distortion ``d(m) (N, 2)`` of base points ``m (N, 2)`` with coefficients ``c (11,)``."""
    x, y, r2, xy2, num, den, _, _ = _parts(m, c)
    p1, p2, s1, s3 = c[7:]
    radial = num / den
    return np.stack([x * radial + p1 * xy2 + p2 * (r2 + 2.0 * x * x) + s1 * r2,
                     y * radial + p1 * (r2 + 2.0 * y * y) + p2 * xy2 + s3 * r2], axis=1)


def distort_with_jacobian(m: np.ndarray, c: np.ndarray) -> Distorted:
    """:func:`distort` with its derivatives w.r.t. the base point and the coefficients."""
    x, y, r2, xy2, num, den, dnum, dden = _parts(m, c)
    p1, p2, s1, s3 = c[7:]
    radial = num / den
    d = distort(m, c)
    dradial = (dnum * den - num * dden) / (den * den)  # d radial / d(r^2)
    d_m = np.empty((len(m), 2, 2))
    d_m[:, 0, 0] = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x + 2.0 * s1 * x
    d_m[:, 0, 1] = xy2 * dradial + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * s1 * y
    d_m[:, 1, 0] = xy2 * dradial + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * s3 * x
    d_m[:, 1, 1] = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x + 2.0 * s3 * y
    d_c = np.zeros((len(m), 2, 11))
    powers = np.stack([r2, r2 * r2, r2 * r2 * r2, r2 * r2 * r2 * r2], axis=1)  # r^2 .. r^8
    d_c[:, 0, 0:4] = (x / den)[:, None] * powers
    d_c[:, 1, 0:4] = (y / den)[:, None] * powers
    d_c[:, 0, 4:7] = -(x * radial / den)[:, None] * powers[:, :3]
    d_c[:, 1, 4:7] = -(y * radial / den)[:, None] * powers[:, :3]
    d_c[:, 0, 7], d_c[:, 1, 7] = xy2, r2 + 2.0 * y * y
    d_c[:, 0, 8], d_c[:, 1, 8] = r2 + 2.0 * x * x, xy2
    d_c[:, 0, 9] = r2
    d_c[:, 1, 10] = r2
    return Distorted(d, d_m, d_c)


def radial_map(r: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The radial map ``g(r) = r radial(r^2)`` of base radii ``r (N,)`` and its slope
    ``g'(r) = radial + 2 r^2 radial'`` (the distortion of a point ``(r, 0)`` without the
    tangential and thin-prism terms)."""
    r2 = r * r
    num, den, dnum, dden = _radial(r2, c)
    return r * num / den, num / den + 2.0 * r2 * (dnum * den - num * dden) / (den * den)


def radial_slope_root(c: np.ndarray, r_of: np.ndarray) -> float:
    """The first base radius where the radial map stops increasing (``g'(r) <= 0``), searched
    along the increasing radii ``r_of (K,)``; ``inf`` when it increases over all of them.

    The root is refined by bisection between the last increasing and the first failing sample.
    """
    slope = radial_map(r_of, c)[1]
    bad = np.flatnonzero(~(slope > 0))
    if len(bad) == 0:
        return float("inf")
    k = int(bad[0])
    if k == 0:
        return 0.0
    lo, hi = float(r_of[k - 1]), float(r_of[k])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if radial_map(np.array([mid]), c)[1][0] > 0:
            lo = mid
        else:
            hi = mid
    return lo
