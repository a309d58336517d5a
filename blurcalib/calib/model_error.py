"""Whether random noise explains a calibration's data: the model-error check (``docs/uncertainty.md``).

The projection uncertainty and the held-out error describe random error only; an error that is
the same from frame to frame (a feature definition that is biased across the field, a camera
model that cannot follow the lens) leaves both small. Two figures say when noise alone does not
explain the data:

* **Residual structure** (:func:`residual_structure`): the inlier residuals of all frames binned
  over the image in ``nx x ny`` cells; per cell the mean residual vector ``m`` and its standard
  error per axis from the cell's own scatter, ``se_i = std_i / sqrt(n)``. Under noise
  ``z = sqrt((m_x / se_x)^2 + (m_y / se_y)^2)`` follows a chi distribution of 2 degrees of
  freedom (``P(z > 4) = exp(-8) = 3.4e-4`` a cell, 0.016 over 48 cells, a Bonferroni-minded
  limit). A cell is systematic when ``z > z_limit`` and ``|m| > floor_px``.
* **Noise against the data** (:func:`noise_ratio`): the cross-validation diff ``d(u)`` of the
  generic cameras of two halves of the frames against what two independent estimates predict,
  ``sqrt(sigma_a(u)^2 + sigma_b(u)^2)``; each half has half the observations, so its
  uncertainty is taken as ``sqrt(2) sigma(u)`` of the camera of all frames, and the prediction
  is ``2 sigma(u)``. The halves are fitted under the bundle adjustment's smoothness prior
  (``smoothness_px``, each around its own initial camera), so ``sigma`` here is the uncertainty
  with that prior (``prior_scale`` 1), an upper bound where the frames are thin: the ratio of
  the RMS of the diff to the RMS of the prediction is below 1 when random noise explains the
  difference (0.6-0.8 on simulated noise); above ``ratio_limit`` it does not.

Pixel convention: OpenCV (the centre of the top-left pixel is ``(0, 0)``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from blurcalib.calib.uncertainty import CrossValidationDiff, ProjectionUncertainty

__all__ = ["ModelError", "ResidualStructure", "model_error", "noise_ratio", "residual_structure"]

Z_LIMIT = 4.0
"""A cell's mean residual, in standard errors, beyond which it is not noise (module docstring)."""
FLOOR_PX = 0.01
"""A cell's mean residual (px) below which it is not named, however many observations it has."""
RATIO_LIMIT = 2.0
"""The halves' diff over what their uncertainties predict beyond which it is named systematic."""


@dataclass(frozen=True)
class ResidualStructure:
    """The inlier residuals' mean per image cell (:func:`residual_structure`).

    Attributes:
        cells: ``(nx, ny)`` cells over the image.
        mean_px: ``(ny, nx, 2)`` px mean residual per cell (NaN with fewer than ``min_count``
            observations); z: ``(ny, nx)`` its size in standard errors; count: ``(ny, nx)``.
        systematic_cells: cells with ``z > z_limit`` and ``|mean| > floor_px``.
        max_mean_px: the largest ``|mean|`` of the cells measured (px).
        z_limit, floor_px: the limits used.
    """

    cells: tuple[int, int]
    mean_px: np.ndarray
    z: np.ndarray
    count: np.ndarray
    systematic_cells: int
    max_mean_px: float
    z_limit: float
    floor_px: float


def residual_structure(xy: np.ndarray, residuals: np.ndarray, size: tuple[int, int],
                       cells: tuple[int, int] = (8, 6), z_limit: float = Z_LIMIT,
                       floor_px: float = FLOOR_PX, min_count: int = 10) -> ResidualStructure:
    """Bin residuals ``(N, 2)`` px at observed positions ``xy`` ``(N, 2)`` px over an image of
    ``size`` ``(width, height)`` in ``cells`` ``(nx, ny)`` and test each cell's mean against
    its standard error (module docstring)."""
    nx, ny = cells
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    r = np.asarray(residuals, dtype=np.float64).reshape(-1, 2)
    ok = np.all(np.isfinite(xy), axis=1) & np.all(np.isfinite(r), axis=1)
    xy, r = xy[ok], r[ok]
    ix = np.clip((xy[:, 0] + 0.5) * nx / size[0], 0, nx - 1).astype(int)
    iy = np.clip((xy[:, 1] + 0.5) * ny / size[1], 0, ny - 1).astype(int)
    cell = iy * nx + ix
    mean = np.full((ny * nx, 2), np.nan)
    z = np.full(ny * nx, np.nan)
    n = np.bincount(cell, minlength=nx * ny)
    for k in np.nonzero(n >= min_count)[0]:
        rk = r[cell == k]
        mean[k] = rk.mean(axis=0)
        se = np.maximum(rk.std(axis=0, ddof=1), 1e-12) / math.sqrt(len(rk))
        z[k] = float(np.hypot(*(mean[k] / se)))
    size_px = np.hypot(mean[:, 0], mean[:, 1])
    measured = np.isfinite(size_px)
    systematic = measured & (np.nan_to_num(z) > z_limit) & (np.nan_to_num(size_px) > floor_px)
    largest = float(size_px[measured].max()) if measured.any() else math.nan
    return ResidualStructure((nx, ny), mean.reshape(ny, nx, 2), z.reshape(ny, nx), n.reshape(ny, nx),
                             int(systematic.sum()), largest, z_limit, floor_px)


def noise_ratio(diff: CrossValidationDiff, unc: ProjectionUncertainty) -> tuple[float, float]:
    """The halves' RMS diff (px) and its ratio to the RMS of ``2 sigma(u)`` (module docstring) over
    the lattice points where both are finite; NaN when none are."""
    px = np.column_stack([diff.x, diff.y])
    predicted = 2.0 * unc.at(px)
    ok = np.isfinite(diff.diff_px) & np.isfinite(predicted)
    if not ok.any():
        return math.nan, math.nan
    rms = float(np.sqrt(np.mean(diff.diff_px[ok] ** 2)))
    pred = float(np.sqrt(np.mean(predicted[ok] ** 2)))
    return rms, rms / pred if pred > 0 else math.nan


@dataclass(frozen=True)
class ModelError:
    """The model-error check of a calibration (module docstring).

    Attributes:
        structure: the residual structure.
        halves_rms_px: RMS of the cross-validation diff (px), NaN without one.
        noise_ratio: ``halves_rms_px`` over what the halves' uncertainties predict, NaN without it.
        ratio_limit: the ratio beyond which it is named systematic.
    """

    structure: ResidualStructure
    halves_rms_px: float = math.nan
    noise_ratio: float = math.nan
    ratio_limit: float = RATIO_LIMIT

    @property
    def systematic(self) -> bool:
        """Whether noise does not explain the data (a systematic cell, or the ratio beyond its limit)."""
        return self.structure.systematic_cells > 0 or (math.isfinite(self.noise_ratio)
                                                       and self.noise_ratio > self.ratio_limit)

    def verdict(self) -> str:
        """The check in plain words."""
        s = self.structure
        nx, ny = s.cells
        parts = []
        if s.systematic_cells:
            parts.append(f"the residuals are not noise in {s.systematic_cells} of {nx * ny} image cells "
                         f"(mean up to {s.max_mean_px:.4f} px, beyond {s.z_limit:g} standard errors)")
        if math.isfinite(self.noise_ratio) and self.noise_ratio > self.ratio_limit:
            parts.append(f"the halves differ by {self.noise_ratio:.1f} x what random noise predicts")
        if parts:
            return "systematic error: " + "; ".join(parts)
        ratio = "" if not math.isfinite(self.noise_ratio) else \
            f"; the halves differ by {self.noise_ratio:.1f} x what random noise predicts"
        return (f"no systematic error seen: no image cell's mean residual beyond {s.z_limit:g} standard "
                f"errors and {s.floor_px:g} px (largest {s.max_mean_px:.4f} px){ratio}")

    def to_dict(self) -> dict[str, Any]:
        """``report.json``'s ``trust.model_error`` section (``docs/results-format.md``)."""
        s = self.structure
        return {"cells": list(s.cells), "systematic_cells": s.systematic_cells,
                "max_cell_mean_px": _round(s.max_mean_px), "z_limit": s.z_limit, "floor_px": s.floor_px,
                "halves_rms_px": _round(self.halves_rms_px), "noise_ratio": _round(self.noise_ratio),
                "ratio_limit": self.ratio_limit, "systematic": self.systematic, "verdict": self.verdict()}


def model_error(xy: np.ndarray, residuals: np.ndarray, size: tuple[int, int],
                cross_validation: CrossValidationDiff | None = None,
                uncertainty: ProjectionUncertainty | None = None) -> ModelError:
    """The residual structure of ``residuals`` ``(N, 2)`` px at ``xy`` ``(N, 2)`` px and, given both
    the halves' diff and the uncertainty, the noise ratio (module docstring)."""
    structure = residual_structure(xy, residuals, size)
    if cross_validation is None or uncertainty is None:
        return ModelError(structure)
    rms, ratio = noise_ratio(cross_validation, uncertainty)
    return ModelError(structure, rms, ratio)


def _round(v: float) -> float | None:
    return round(float(v), 5) if math.isfinite(v) else None
