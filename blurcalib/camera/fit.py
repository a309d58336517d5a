"""A parametric camera of the family fitted to known rays: how well a model can describe a lens.

Given pixels ``u_i (N, 2)`` and their unit rays ``v_i (N, 3)`` (of a true lens, or of a generic
camera), minimise over the model's intrinsics ``theta`` and a rotation ``R`` (a central camera's
orientation is a gauge, absorbed by the poses of a calibration)::

    sum_i |pi_theta(R v_i) - u_i|^2        (px^2)

by Levenberg-Marquardt with the model's analytic Jacobian. The start: the principal point at the
image centre, no distortion, the focal length of the rays up to 45 degrees off the axis. A
perspective model cannot see rays at 90 degrees or more; they are left out of the fit, and
:attr:`RayFit.covered` says what share of the pixels the fitted model describes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import least_squares

from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import rodrigues_jacobian

__all__ = ["RayFit", "fit_rays"]

_PERSPECTIVE_LIMIT = 0.05
"""Rays with ``Z`` below this (beyond about 87 degrees off the axis) are left out of a
perspective model's fit."""


@dataclass(frozen=True, eq=False)
class RayFit:
    """A model fitted to rays.

    Attributes:
        camera: the fitted camera.
        rotation: ``(3, 3)`` the rays' rotation into the camera's frame.
        errors: ``(N,)`` px ``|pi(R v_i) - u_i|``, NaN where the fitted model does not see the ray
            in its valid field.
        covered: share of the rays the model sees in its valid field.
    """

    camera: ParametricCamera
    rotation: np.ndarray
    errors: np.ndarray
    covered: float

    @property
    def median(self) -> float:
        """Median error (px) over the covered rays."""
        ok = np.isfinite(self.errors)
        return float(np.median(self.errors[ok])) if ok.any() else float("nan")

    @property
    def max(self) -> float:
        """Largest error (px) over the covered rays."""
        ok = np.isfinite(self.errors)
        return float(self.errors[ok].max()) if ok.any() else float("nan")


def _start(model: type[ParametricCamera], px: np.ndarray, rays: np.ndarray, width: int, height: int
           ) -> ParametricCamera:
    """The fit's start: centred principal point, no distortion, the rays' focal length."""
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    theta = np.arccos(np.clip(rays[:, 2], -1.0, 1.0))
    near = (theta > 1e-3) & (theta < np.radians(45.0))
    radius = np.linalg.norm(px - centre, axis=1)
    probe = model(np.r_[1.0, 1.0, centre, np.zeros(len(model.PARAM_NAMES) - 4)], width, height)
    scale = theta if probe.angular else np.tan(theta)
    f = float(np.median(radius[near] / scale[near])) if near.any() else float(max(width, height))
    return probe.with_params(np.r_[f, f, centre, np.zeros(len(model.PARAM_NAMES) - 4)])


def fit_rays(model: type[ParametricCamera], px: ArrayLike, rays: ArrayLike, width: int, height: int,
             start: ParametricCamera | None = None, rotate: bool = True) -> RayFit:
    """Fit ``model`` to pixels ``px (N, 2)`` and their rays ``rays (N, 3)`` (module docstring).

    Args:
        model: the model class (e.g. :class:`blurcalib.camera.kannala_brandt.KannalaBrandtCamera`).
        px, rays: the samples; rays need not be unit, non-finite ones are skipped.
        width, height: the image size (px).
        start: the start (default: module docstring).
        rotate: whether to fit the rotation too (else ``R = I``).
    """
    pixels = np.asarray(px, dtype=np.float64).reshape(-1, 2)
    units = np.asarray(rays, dtype=np.float64).reshape(-1, 3)
    units = units / np.linalg.norm(units, axis=1, keepdims=True)
    usable = np.all(np.isfinite(units), axis=1)
    camera = start if start is not None else _start(model, pixels[usable], units[usable], width, height)
    if not camera.angular:
        usable &= units[:, 2] > _PERSPECTIVE_LIMIT
    u, v = pixels[usable], units[usable]
    n_intr = len(camera.params)

    def unpack(x: np.ndarray) -> tuple[ParametricCamera, np.ndarray, np.ndarray]:
        R, dR = rodrigues_jacobian(x[n_intr:][None] if rotate else np.zeros((1, 3)))
        return camera.with_params(x[:n_intr]), R[0], dR[0]

    def residual(x: np.ndarray) -> np.ndarray:
        cam, R, _ = unpack(x)
        return (cam.project(v @ R.T) - u).ravel()

    def jacobian(x: np.ndarray) -> np.ndarray:
        cam, R, dR = unpack(x)
        proj = cam.project_with_jacobian(v @ R.T)
        assert proj.d_intrinsics is not None and proj.d_point is not None
        blocks = [proj.d_intrinsics]
        if rotate:
            blocks.append(np.einsum("nij,kjl,nl->nik", proj.d_point, dR, v))
        return np.concatenate(blocks, axis=2).reshape(-1, n_intr + (3 if rotate else 0))

    x0 = np.r_[camera.params, np.zeros(3)] if rotate else camera.params.copy()
    sol = least_squares(residual, x0, jac=jacobian, method="lm", x_scale="jac", max_nfev=400)
    fitted, R, _ = unpack(sol.x)
    turned = units @ R.T
    valid = np.all(np.isfinite(turned), axis=1)
    valid[valid] = fitted.valid_directions(turned[valid])
    errors = np.full(len(pixels), np.nan)
    errors[valid] = np.linalg.norm(fitted.project(turned[valid]) - pixels[valid], axis=1)
    return RayFit(fitted, R, errors, float(valid.mean()))
