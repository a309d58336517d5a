"""The bias models of global alignment: a translation of a frame's features that varies over the
target (supplement B), ``b(i, j) = phi(i, j) beta`` per image axis (px).

``(i, j) in [-1, 1]^2`` are normalised grid coordinates (:func:`grid_coordinates`); the models
(:data:`BIASES`, bases :func:`bias_basis`) are none, one translation, the bilinear field
``(1, i, j, i j)`` (``eq:bilinear_bias``) and one translation per quadrant. Their coefficients are
fitted with the pose by :func:`blurcalib.calib.alignment.align_global`.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from numpy.typing import ArrayLike

from blurcalib.target.pattern import StarPattern

__all__ = ["BIASES", "beta_from_coeffs", "bias_basis", "bias_field", "coeffs_from_beta", "grid_coordinates"]

BIASES: tuple[str, ...] = ("none", "translation", "bilinear", "quadrants")
"""Bias models: pose only, one translation, the bilinear field, one translation per quadrant."""


def grid_coordinates(pattern: StarPattern, features: ArrayLike) -> np.ndarray:
    """Normalised grid coordinates ``(i, j) in [-1, 1]^2`` of features (supplement B).

    Args:
        pattern: the target; its valid features span ``0 <= fx <= squares_x - 2`` and
            ``0 <= fy <= squares_y - 2``.
        features: ``(N, 2)`` feature coordinates ``(fx, fy)`` (squares, ``pattern.features``).

    Returns:
        ``(N, 2)``: column 0 is ``i = 2 fx / (squares_x - 2) - 1`` (along the target's x),
        column 1 is ``j = 2 fy / (squares_y - 2) - 1`` (along its y).
    """
    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2 or f.shape[1] != 2:
        raise ValueError(f"features must have shape (N, 2), got {f.shape}")
    extent = np.array([pattern.squares_x - 2, pattern.squares_y - 2], dtype=np.float64)
    return 2.0 * f / extent - 1.0


def bias_basis(grid: ArrayLike | None, bias: str, n: int) -> np.ndarray:
    """Basis ``phi`` of a bias model at ``n`` features, shape ``(n, B)``.

    * ``"none"``: ``B = 0``; ``"translation"``: ``phi = 1``;
    * ``"bilinear"``: ``phi(i, j) = (1, i, j, i j)`` (supplement B);
    * ``"quadrants"``: indicators of the quadrants, in the order top-left ``(i < 0, j < 0)``,
      top-right ``(i >= 0, j < 0)``, bottom-left ``(i < 0, j >= 0)``, bottom-right.

    Args:
        grid: ``(n, 2)`` normalised grid coordinates (:func:`grid_coordinates`); needed for
            ``"bilinear"`` and ``"quadrants"`` only.
        bias: one of :data:`BIASES`.
        n: number of features.
    """
    if bias not in BIASES:
        raise ValueError(f"bias must be one of {BIASES}, got {bias!r}")
    if bias == "none":
        return np.zeros((n, 0))
    if bias == "translation":
        return np.ones((n, 1))
    if grid is None:
        raise ValueError(f"bias {bias!r} needs the features' grid coordinates")
    g = np.asarray(grid, dtype=np.float64)
    if g.shape != (n, 2):
        raise ValueError(f"grid must have shape ({n}, 2), got {g.shape}")
    i, j = g[:, 0], g[:, 1]
    if bias == "bilinear":
        return np.stack([np.ones(n), i, j, i * j], axis=1)
    right = i >= 0
    down = j >= 0
    return np.stack([~right & ~down, right & ~down, ~right & down, right & down], axis=1).astype(float)


def coeffs_from_beta(beta: np.ndarray, bias: str) -> np.ndarray:
    """Internal parameters ``(b_x (B,), b_y (B,))`` -> the public ``bias_coeffs`` layout."""
    per_axis = beta.reshape(2, -1)
    if bias == "none":
        return np.zeros(0)
    if bias == "translation":
        return per_axis[:, 0].copy()
    if bias == "bilinear":
        return per_axis.copy()
    return per_axis.T.copy()


def beta_from_coeffs(coeffs: ArrayLike, bias: str) -> np.ndarray:
    """Inverse of :func:`coeffs_from_beta`."""
    c = np.asarray(coeffs, dtype=np.float64)
    expected = {"none": (0,), "translation": (2,), "bilinear": (2, 4), "quadrants": (4, 2)}[bias]
    if c.shape != expected:
        raise ValueError(f"{bias} coefficients must have shape {expected}, got {c.shape}")
    if bias == "quadrants":
        return c.T.reshape(-1).copy()
    return c.reshape(-1).copy()


def bias_field(grid: ArrayLike | None, bias: str, coeffs: ArrayLike, n: int | None = None) -> np.ndarray:
    """Evaluate a bias model: ``b = phi(i, j) coeffs`` per axis, ``(n, 2)`` px.

    Args:
        grid: ``(n, 2)`` normalised grid coordinates (may be None for ``"none"`` and
            ``"translation"``, then ``n`` is required).
        bias: one of :data:`BIASES`.
        coeffs: ``bias_coeffs`` as in :class:`blurcalib.calib.alignment.GlobalAlignment` (px):
            ``(0,)``, ``(2,)``, ``(2, 4)`` (rows x, y over ``(1, i, j, ij)``) or ``(4, 2)``
            (quadrant rows, x y).
        n: number of features, when ``grid`` is None.
    """
    if n is None:
        if grid is None:
            raise ValueError("give grid or n")
        n = int(np.asarray(grid).shape[0])
    phi = bias_basis(grid, bias, n)
    beta = beta_from_coeffs(coeffs, bias).reshape(2, -1)
    return cast(np.ndarray, phi @ beta.T)
