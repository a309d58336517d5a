"""Accuracy of extracted or aligned features against a simulated dataset's ground truth.

The figure of merit for aligned blurry-frame features is the reprojection error against the
*true* camera (Brown-Conrady plus its non-parametric deviation) with each frame's pose refitted
to the features: it measures the features' error, not the pose's or the parametric model's.
The figure of merit of a calibrated camera is :func:`projection_errors`: how far it projects
each pixel's true ray, after the best-fit rotation (a central camera's orientation is a gauge).
:func:`camera_accuracy` also splits that error field ``e(x)`` into its best-fit affine part
``a + A (x - c)`` (a change of focal lengths, skew and principal point: a pinhole's linear
intrinsics) and the rest, the error of the camera's *shape*: a focal length off by 1e-4 moves
the image corners by 0.07 px, and is hard to pin down from any set of frames, so it dominates
the total error of an otherwise accurate generic camera.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from scipy.optimize import least_squares

from blurcalib.camera.generic import CentralGeneric, best_fit_rotation
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.geometry.homography import apply_homography
from blurcalib.geometry.pose import Pose
from blurcalib.io.results import FeatureFlags, FeatureTable
from blurcalib.sim.truth import DatasetTruth, TrueCamera
from blurcalib.target.pattern import StarPattern


@dataclass(frozen=True)
class FrameAccuracy:
    """Per-frame accuracy (px).

    Attributes:
        frame: frame name.
        count: features evaluated.
        median, p90, max: of the reprojection error with the pose refitted under the true camera.
        median_vs_mean: median distance to the ground-truth time-averaged positions after
            removing the frame's mean offset.
    """

    frame: str
    count: int
    median: float
    p90: float
    max: float
    median_vs_mean: float


def pose_consistent_errors(xy: np.ndarray, truth_xy: np.ndarray) -> np.ndarray:
    """``(B,)`` px: distances of one frame's extracted star centres ``xy (B, 2)`` to their true
    time-averaged positions ``truth_xy (B, 2)`` after the frame's best-fit homography truth ->
    extracted (least median of squares): a pose change of the planar target, which a calibration
    refits (to first order in the sub-pixel change, the lens does not bend it). With fewer than 8
    features, after their mean offset instead."""
    if len(xy) < 8:
        d = xy - truth_xy
        return cast(np.ndarray, np.linalg.norm(d - d.mean(axis=0), axis=1))
    H, _ = cv2.findHomography(truth_xy.astype(np.float64), xy.astype(np.float64), cv2.LMEDS)
    return cast(np.ndarray, np.linalg.norm(xy - apply_homography(H, truth_xy), axis=1))


def refit_pose(camera: TrueCamera, points: np.ndarray, xy: np.ndarray, start: Pose) -> Pose:
    """Least-squares pose under the true camera: ``argmin_M sum |pi(M P) - x|^2``."""
    def residual(v: np.ndarray) -> np.ndarray:
        R, _ = cv2.Rodrigues(v[:3])
        return cast(np.ndarray, (camera.project(points @ R.T + v[3:]) - xy).ravel())

    sol = least_squares(residual, np.concatenate([start.rvec, start.t]), method="lm")
    return Pose.from_rvec_tvec(sol.x[:3], sol.x[3:])


def evaluate_features(features: FeatureTable, truth: DatasetTruth, pattern: StarPattern,
                      required_flags: int = int(FeatureFlags.GLOBALLY_ALIGNED),
                      skip_flags: int = int(FeatureFlags.FILTERED_OUT)) -> list[FrameAccuracy]:
    """Evaluate every frame's features that carry ``required_flags`` and none of ``skip_flags``."""
    keep = ((features.flags & required_flags) == required_flags) & ((features.flags & skip_flags) == 0)
    out = []
    for name in sorted(set(features.frame[keep].tolist())):
        rows = np.flatnonzero(keep & (features.frame == name))
        if len(rows) < 6:
            continue
        frame = truth.frame(name)
        ids = features.feature_id[rows]
        xy = np.stack([features.x[rows], features.y[rows]], axis=1)
        pose = refit_pose(truth.camera, pattern.points_3d(ids), xy, frame.pose)
        err = np.linalg.norm(truth.camera.project(pose.transform(pattern.points_3d(ids))) - xy, axis=1)
        d = xy - frame.mean[ids]
        d -= d.mean(axis=0)
        out.append(FrameAccuracy(name, len(rows), float(np.median(err)),
                                 float(np.percentile(err, 90)), float(err.max()),
                                 float(np.median(np.linalg.norm(d, axis=1)))))
    return out


def pixel_lattice(width: int, height: int, step: float) -> np.ndarray:
    """``(N, 2)`` pixels every ``step`` px over a ``width x height`` image (OpenCV convention)."""
    xs = np.arange(0.0, width - 1 + 1e-9, step)
    ys = np.arange(0.0, height - 1 + 1e-9, step)
    xx, yy = np.meshgrid(xs, ys)
    return np.column_stack([xx.ravel(), yy.ravel()])


def projection_errors(truth: TrueCamera, estimate: BrownConrady | ParametricCamera | CentralGeneric,
                      px: np.ndarray) -> np.ndarray:
    """``(N,)`` px: the norms of :func:`projection_error_vectors`."""
    return cast(np.ndarray, np.linalg.norm(projection_error_vectors(truth, estimate, px), axis=1))


def projection_error_vectors(truth: TrueCamera, estimate: BrownConrady | ParametricCamera | CentralGeneric,
                             px: np.ndarray) -> np.ndarray:
    """``(N, 2)`` px: the estimate's projection of each pixel ``px (N, 2)``'s true ray, after the
    best-fit rotation, minus the pixel. NaN where the estimate is undefined (outside a generic
    model's calibrated area)."""
    rays = truth.pixel_to_ray(px)
    est = estimate.pixel_to_ray(px)
    ok = np.all(np.isfinite(est), axis=1)
    turned = rays @ best_fit_rotation(rays[ok], est[ok]).T
    if isinstance(estimate, CentralGeneric):
        u, inside = estimate.project(turned)
        err = u - px
        err[~inside | ~ok] = np.nan
        return cast(np.ndarray, err)
    return cast(np.ndarray, estimate.project(turned) - px)


@dataclass(frozen=True)
class CameraAccuracy:
    """A calibrated camera against the true one over the image (:func:`projection_errors`).

    Attributes:
        median, p95, max: px over the pixels where the camera is defined.
        defined: share of the image's pixels where it is defined (a generic model's calibrated
            area; 1 for a parametric camera).
        shape_median: px, median error after removing the best-fit affine part of the error
            field (focal lengths, skew, principal point; see the module docstring).
        scale_px: px, the affine part's isotropic scale at the image corner (mean of its two
            diagonal terms times the centre-corner distance): a focal length error.
    """

    median: float
    p95: float
    max: float
    defined: float
    shape_median: float
    scale_px: float


def camera_accuracy(truth: TrueCamera, estimate: BrownConrady | ParametricCamera | CentralGeneric,
                    step: float = 8.0) -> CameraAccuracy:
    """:func:`projection_errors` on a lattice every ``step`` px over the true camera's image."""
    model = truth.model
    px = pixel_lattice(model.width, model.height, step)
    vec = projection_error_vectors(truth, estimate, px)
    ok = np.all(np.isfinite(vec), axis=1)
    if not ok.any():
        return CameraAccuracy(float("nan"), float("nan"), float("nan"), 0.0, float("nan"), float("nan"))
    e = np.linalg.norm(vec[ok], axis=1)
    corner = np.array([model.width - 1, model.height - 1]) / 2.0
    design = np.column_stack([np.ones(int(ok.sum())), px[ok] - corner])
    coef, *_ = np.linalg.lstsq(design, vec[ok], rcond=None)  # e ~ a + A (x - c), coef (3, 2)
    shape = np.linalg.norm(vec[ok] - design @ coef, axis=1)
    scale = 0.5 * (coef[1, 0] + coef[2, 1]) * float(np.linalg.norm(corner))
    return CameraAccuracy(float(np.median(e)), float(np.percentile(e, 95)), float(e.max()), float(ok.mean()),
                          float(np.median(shape)), float(scale))
