"""How far a calibrated rig's extrinsics can be trusted: their uncertainty and their held-out error.

Uncertainty. The joint bundle gives the covariance ``Sigma (6 (C-1), 6 (C-1))`` of the extrinsics
of cameras ``1 .. C-1`` (:class:`blurcalib.calib.rig_bundle.RigBundleResult`: per camera the
rotation increment ``omega_c`` with ``R_c <- exp(omega_c) R_c`` and ``dt_c``; camera 0's are fixed).
A pair's pose ``camera j <- camera i``, ``R = R_j R_i^T``, ``t = t_j - R t_i``, moves to first order
by the rotation ``omega = omega_j - R omega_i`` and the translation
``dt = dt_j - R dt_i + [R t_i]_x omega`` (:func:`pair_uncertainty`); its uncertainty is the root
of the trace of that covariance's rotation and translation blocks: the expected size of the
rotation error (deg) and of the translation error (mm).

The joint bundle holds each camera's own calibration fixed, so its covariance counts the
features' noise with exact cameras. Each camera's own error moves the extrinsics too
(:func:`cameras_covariance`): with ``theta_c`` camera ``c``'s grid parameters, their covariance
``Sigma_c`` from the camera's own calibration with its rotation removed
(:func:`blurcalib.calib.uncertainty.grid_covariance`, a central camera's orientation being a gauge
that the extrinsics take up) and the extrinsics' sensitivity ``D_c = dE/dtheta_c``
(:func:`blurcalib.calib.rig_bundle.camera_sensitivity`, the implicit-function theorem at the
joint bundle's solution)::

    Sigma_E = Sigma_E,features + sum_c D_c Sigma_c D_c^T

the cameras' errors taken as independent of each other and of the joint bundle's noise.

Held-out error (:func:`rig_holdout`). The sets seen by two or more cameras are split into ``k``
folds (every ``k``-th set); for each fold the rig is fitted without the fold's sets
(:func:`blurcalib.calib.rig_calibration.rig_problem`), then in each held-out set each camera's
own target pose (its calibration's, from that camera alone) predicts the features of every other
camera seeing the set through the fitted extrinsics: ``r = p - pi_b(T_b T_a^-1 M_a P)`` px
(OpenCV convention). A blurry frame's image shift is free, so its residuals' median is taken out.
A pair's held-out error is the median ``|r|`` over both directions. With exact cameras and
features of Gaussian noise ``sigma`` px per axis it is about ``1.18 sigma`` (the median of a 2-D
Gaussian's radius) plus the one-camera poses' own error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from blurcalib.calib.bundle import BundleSettings
from blurcalib.calib.rig_bundle import camera_sensitivity, rig_bundle_adjust
from blurcalib.calib.rig_calibration import RigCalibration, RigError, rig_problem
from blurcalib.calib.trust import TrustSettings
from blurcalib.calib.uncertainty import grid_covariance
from blurcalib.camera.rig import Rig

__all__ = ["PairTrust", "cameras_covariance", "pair_uncertainty", "rig_holdout", "rig_trust"]


def pair_uncertainty(rig: Rig, covariance: np.ndarray, i: int, j: int) -> tuple[float, float]:
    """``(translation_mm, rotation_deg)``: the expected size of the errors of ``camera j <- camera i``
    from the extrinsics' covariance ``(6 (C-1), 6 (C-1))`` (module docstring); NaN if unknown."""
    C = rig.size
    if covariance.shape != (6 * (C - 1), 6 * (C - 1)) or not np.all(np.isfinite(covariance)):
        return math.nan, math.nan
    rel = rig.relative(i, j)
    J = np.zeros((6, 6 * (C - 1)))
    if j > 0:
        J[:, 6 * (j - 1):6 * j] = np.eye(6)
    if i > 0:
        block = np.zeros((6, 6))
        block[:3, :3] = -rel.R
        block[3:, 3:] = -rel.R
        J[:, 6 * (i - 1):6 * i] += block
    x, y, z = rel.R @ rig.camera_tr_rig[i].t
    J[3:, :] += np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]) @ J[:3, :]
    cov = J @ covariance @ J.T
    return (float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0))) * 1000.0,
            float(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0)))))


def cameras_covariance(calibration: RigCalibration, settings: BundleSettings | None = None,
                       prior_scale: float = TrustSettings.prior_scale) -> np.ndarray:
    """``(6 (C-1), 6 (C-1))``: the covariance that the cameras' own calibration errors add to the
    extrinsics (module docstring; ``settings`` the joint bundle's, ``prior_scale`` the cameras'
    :func:`blurcalib.calib.uncertainty.grid_covariance`'s, by default ``calibrate``'s); NaN where a
    camera's covariance cannot be computed (its grid singular)."""
    bundle = calibration.bundle
    G = 6 * (bundle.rig.size - 1)
    observations = rig_problem(calibration.cameras)[3]
    total = np.zeros((G, G))
    try:
        sensitivity = camera_sensitivity(bundle, observations, settings)
        for cal, D in zip(calibration.cameras, sensitivity, strict=True):
            Sigma = grid_covariance(cal.bundle, prior_scale).cpu().numpy()
            total += D @ Sigma @ D.T
    except (ValueError, RuntimeError):  # torch.linalg.LinAlgError is a RuntimeError
        return np.full((G, G), math.nan)
    return 0.5 * (total + total.T)


def _predicted_errors(rig: Rig, calibration: RigCalibration, names: set[str], a: int, b: int
                      ) -> list[np.ndarray]:
    """Camera ``b``'s held-out errors ``|r| (n,)`` px predicted from camera ``a``'s poses of ``names``."""
    cal_a, cal_b = calibration.cameras[a], calibration.cameras[b]
    between = rig.relative(a, b)
    out = []
    for name in sorted(names & set(cal_a.poses) & set(cal_b.frames)):
        rows = (cal_b.frame == name) & cal_b.inlier
        if not rows.any():
            continue
        X = between.compose(cal_a.poses[name]).transform(cal_b.points[rows])
        u, inside = cal_b.model.project(X)
        r = cal_b.observed[rows][inside] - u[inside]
        if len(r) and name in cal_b.blurry_frames:
            r = r - np.median(r, axis=0)
        out.append(np.linalg.norm(r, axis=1))
    return out


def rig_holdout(calibration: RigCalibration, folds: int = 5, settings: BundleSettings | None = None
                ) -> dict[tuple[int, int], tuple[float, int]]:
    """Each pair ``(i, j)`` (``i < j``) sharing held-out sets: ``(median error px, predictions)``
    of its extrinsics on the sets left out, ``folds``-fold (module docstring). A fold whose
    training sets no longer link every camera is skipped."""
    cams = calibration.cameras
    C = len(cams)
    shared = [n for n in calibration.sets if sum(n in cal.poses for cal in cams) >= 2]
    errors: dict[tuple[int, int], list[np.ndarray]] = {}
    for f in range(min(folds, len(shared))):
        held = set(shared[f::folds])
        try:
            _, camera_tr_rig, rig_tr_global, observations = rig_problem(cams, held)
        except RigError:
            continue
        fitted = rig_bundle_adjust([cal.model for cal in cams], camera_tr_rig, rig_tr_global, observations,
                                   settings).rig
        for i in range(C):
            for j in range(i + 1, C):
                both = (_predicted_errors(fitted, calibration, held, i, j)
                        + _predicted_errors(fitted, calibration, held, j, i))
                errors.setdefault((i, j), []).extend(both)
    out = {}
    for pair, parts in errors.items():
        e = np.concatenate(parts) if parts else np.zeros(0)
        if len(e):
            out[pair] = (float(np.median(e)), len(e))
    return out


@dataclass(frozen=True)
class PairTrust:
    """One pair's trust: ``camera j <- camera i``'s uncertainty (``translation_mm``,
    ``rotation_deg``: expected error sizes) and held-out error (``holdout_px`` median over
    ``holdout_count`` predicted features; NaN and 0 when not measured)."""

    i: int
    j: int
    translation_mm: float
    rotation_deg: float
    holdout_px: float
    holdout_count: int

    def to_dict(self) -> dict[str, Any]:
        return {"cameras": [self.i, self.j], "translation_uncertainty_mm": self.translation_mm,
                "rotation_uncertainty_deg": self.rotation_deg, "holdout_error_px": self.holdout_px,
                "holdout_predictions": self.holdout_count}


def rig_trust(calibration: RigCalibration, folds: int = 5, settings: BundleSettings | None = None,
              cameras: bool = True) -> list[PairTrust]:
    """Every pair's :class:`PairTrust` (``folds = 0``: the uncertainty only); ``cameras``: the
    cameras' own errors folded into the uncertainty (module docstring; False: the features' noise
    alone, for exact cameras)."""
    bundle = calibration.bundle
    held = rig_holdout(calibration, folds, settings) if folds > 0 else {}
    covariance = bundle.covariance + (cameras_covariance(calibration, settings) if cameras else 0.0)
    out = []
    for i in range(bundle.rig.size):
        for j in range(i + 1, bundle.rig.size):
            mm, deg = pair_uncertainty(bundle.rig, covariance, i, j)
            px, n = held.get((i, j), (math.nan, 0))
            out.append(PairTrust(i, j, mm, deg, px, n))
    return out
