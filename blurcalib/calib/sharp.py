"""Parametric (Brown-Conrady) calibration of the sharp set, with the target's 3D points.

The paper calibrates a parametric camera ``pi_d`` and the target's 3D points ``P`` from a small
sharp set; global alignment of the blurry frames then measures every observation against
``pi_d(M, P)``. This module does that calibration.

Model (``Brown_Conrady`` in the paper, OpenCV convention, see :mod:`blurcalib.camera.parametric`)::

    p = pi_d(M_f, P_j) = K (d([R_f P_j + t_f]~), 1)
    d(x) = (1 + k1 r^2 + k2 r^4 + k3 r^6) x + (2 p1 x y + p2 (r^2 + 2 x^2), p1 (r^2 + 2 y^2) + 2 p2 x y)

for frame ``f`` with pose ``M_f = [R_f | t_f]`` (target -> camera, metres; ``R_f`` from the
Rodrigues vector ``rvec_f``) and target point ``P_j`` (metres) of feature ``j``.

Method (:func:`calibrate_sharp`):

1. **Initialisation** by ``cv2.calibrateCamera`` on the planar correspondences
   ``(X, Y, 0) <-> (x, y)`` of every usable frame (``>= min_features`` observations): Zhang's
   method, whose start comes from the plane homographies ``H = K [r1 r2 t]`` (``eq:T``). If some
   observations are gross outliers of that fit (the rule below) it is run once more without them
   and the first adjustment round leaves them out.
2. **Robust bundle adjustment** by Levenberg-Marquardt with Huber weights
   (:mod:`blurcalib.calib.parametric_adjustment`: sparse analytic Jacobian, Marquardt's damping,
   the poses eliminated by the Schur complement and the rest solved directly) over the intrinsics
   ``(fx, fy, cx, cy, k1, k2, p1, p2, k3)``, the poses ``(rvec_f, tvec_f)`` and, with
   ``refine_points``, every observed 3D point ``P_j = (X, Y, Z)`` (``Z`` free: the printed target
   may be slightly non-flat). It minimises::

       sum_{f,j} rho(pi_d(M_f, P_j) - p_fj) + sum_j rho(|P_j - P_j^0| / sigma_P)

   with ``rho`` Huber at ``huber_px`` (``loss='huber'``, applied per residual component; or
   plain squares with ``loss='linear'``) and the nominal grid point ``P_j^0 = (fx L, fy L, 0)``.
3. **Gauge.** With free points the problem is invariant under a similarity of the target frame
   (``P -> s Q P + b`` with ``R_f -> R_f Q^T``, ``t_f -> s t_f - R_f Q^T b``: 7 degrees of
   freedom). The weak prior ``sigma_P`` (default 1 mm, far looser than what the data pins, so
   it biases nothing measurable) keeps the normal equations regular and holds points seen in
   a single frame at their nominal position along the ray; after the fit the gauge is fixed
   exactly: the similarity that best maps the refined points onto the nominal grid in least
   squares (Umeyama) is applied to points and poses. The refined points therefore keep the
   nominal target's centroid, orientation and scale in the least-squares sense; no single point
   is held fixed, so no single feature's error sets the metric scale.
4. **Outliers.** After each fit the error ``e_i = |p_i - pi_d(M, P)|`` of every observation is
   compared with ``5 sigma``, ``sigma = median(e_inliers) / sqrt(2 ln 2) * sqrt(2 n / (2 n - p))``
   (the median of a 2-D Gaussian error norm is ``1.1774 sigma``; the second factor undoes the
   ``p`` parameters' absorption of the noise of ``n`` inliers). Observations above it (and
   above 0.01 px) are outliers, the rest inliers (rejected ones may return), and the fit is
   repeated until the inlier set is stable: no observation changes side, or at most 1e-4 of
   them do, each within 1.5 x of the threshold
   (:func:`blurcalib.calib.parametric_adjustment.adjust`).

Residuals are reported as ``observed - predicted`` (the paper's ``p - pi_d(M, P)``) in pixels
(OpenCV pixel-centre convention).
"""

from __future__ import annotations

import itertools
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike

from blurcalib.calib.parametric_adjustment import ParametricProblem, adjust, gauge_fixed, robust_threshold
from blurcalib.camera.parametric import (
    BrownConrady,
    CameraFileError,
    load_camera_json,
    project_poses,
    save_camera_json,
    save_camera_yaml,
)
from blurcalib.geometry.pose import Pose
from blurcalib.io.atomic import atomic_write_csv, atomic_write_text, ensure_writable_dir, read_csv_columns
from blurcalib.io.results import FeatureFlags, FeatureObservation, FeatureTable
from blurcalib.target.pattern import StarPattern

__all__ = [
    "CALIBRATION_FILE",
    "CAMERA_JSON_FILE",
    "CAMERA_YAML_FILE",
    "POINTS_FILE",
    "RESIDUALS_FILE",
    "Calibration",
    "CalibrationError",
    "CalibrationFileError",
    "calibrate_sharp",
    "load_calibration",
    "reprojection_errors",
    "save_calibration",
    "solve_pose",
]

CAMERA_YAML_FILE = "camera.yaml"
CAMERA_JSON_FILE = "camera.json"
POINTS_FILE = "points.csv"
RESIDUALS_FILE = "residuals.csv"
CALIBRATION_FILE = "calibration.json"

_POINT_COLUMNS = ("feature_id", "X", "Y", "Z", "refined")
_RESIDUAL_COLUMNS = ("frame", "feature_id", "x", "y", "dx", "dy", "inlier")


class CalibrationError(ValueError):
    """The observations cannot be calibrated (too few usable frames); the message says why."""


class CalibrationFileError(ValueError):
    """A calibration folder's file is missing or malformed; the message names the file."""


@dataclass(eq=False)
class Calibration:
    """A calibrated Brown-Conrady camera, the sharp frames' poses and the refined target points.

    Attributes:
        camera: the calibrated camera ``pi_d`` (``Brown_Conrady``).
        poses: frame name -> pose ``M_f`` (target -> camera, metres), calibrated frames only.
        points: ``(M, 3)`` metric target points (m), row ``j`` for feature id ``j`` of the
            pattern; NaN for features not observed in any calibrated frame.
        point_ids: ``(K,)`` sorted ids of the observed features (the finite rows of ``points``).
        point_refined: ``(M,)`` bool, the point was a free parameter (else nominal or NaN).
        frame: ``(N,)`` str, frame of each observation of the calibrated frames.
        feature_id: ``(N,)`` int, feature id of each observation.
        observed: ``(N, 2)`` px, observed positions.
        residuals: ``(N, 2)`` px, ``observed - pi_d(M_f, P_j)``.
        inlier: ``(N,)`` bool, the observation was used in the final fit.
        median_error: px, median of ``|residual|`` over inliers.
        rms_error: px, ``sqrt(mean |residual|^2)`` over inliers.
        num_frames: number of calibrated frames.
        num_observations: ``N``, observations of the calibrated frames (outliers included).
        iterations: trust-region iterations (Jacobian evaluations) over all rounds.
        rounds: bundle-adjustment rounds (outlier rejection and refit).
        refine_points, loss, huber_px: the settings of the fit.
        skipped_frames: frame name -> observation count of frames left out (too few features).
    """

    camera: BrownConrady
    poses: dict[str, Pose]
    points: np.ndarray
    point_ids: np.ndarray
    point_refined: np.ndarray
    frame: np.ndarray
    feature_id: np.ndarray
    observed: np.ndarray
    residuals: np.ndarray
    inlier: np.ndarray
    median_error: float
    rms_error: float
    num_frames: int
    num_observations: int
    iterations: int
    rounds: int
    refine_points: bool
    loss: str
    huber_px: float
    skipped_frames: dict[str, int]

    @property
    def errors(self) -> np.ndarray:
        """``(N,)`` px, reprojection error norms ``|residual|``."""
        return np.linalg.norm(self.residuals, axis=1)

    def frame_errors(self) -> dict[str, dict[str, Any]]:
        """Per calibrated frame: observation and inlier counts, median and RMS inlier error (px)."""
        errors = self.errors
        out: dict[str, dict[str, Any]] = {}
        for name in self.poses:
            rows = self.frame == name
            inl = errors[rows & self.inlier]
            out[name] = {"num_observations": int(rows.sum()), "num_inliers": int(inl.size),
                         "median_error_px": float(np.median(inl)) if inl.size else None,
                         "rms_error_px": float(np.sqrt(np.mean(inl**2))) if inl.size else None}
        return out

    def flatness(self) -> tuple[float, float]:
        """RMS and largest distance (m) of the observed points from their best-fit plane."""
        pts = self.points[self.point_ids]
        if len(pts) < 3:
            return 0.0, 0.0
        centred = pts - pts.mean(axis=0)
        normal = np.linalg.svd(centred, full_matrices=False)[2][2]
        dist = np.abs(centred @ normal)
        return float(np.sqrt(np.mean(dist**2))), float(dist.max())

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable report: camera, errors (px), settings, per-frame poses and errors.

        Poses are ``rvec`` (Rodrigues, rad) and ``tvec`` (m) of ``X_cam = R X + t``.
        """
        per_frame = self.frame_errors()
        for name, pose in self.poses.items():
            per_frame[name] = {"rvec": pose.rvec.tolist(), "tvec": pose.t.tolist(), **per_frame[name]}
        flat_rms, flat_max = self.flatness()
        return {
            "model": "Brown_Conrady",
            "camera": self.camera.to_dict(),
            "median_error_px": self.median_error,
            "rms_error_px": self.rms_error,
            "num_frames": self.num_frames,
            "num_observations": self.num_observations,
            "num_inliers": int(self.inlier.sum()),
            "num_outliers": int((~self.inlier).sum()),
            "iterations": self.iterations,
            "rounds": self.rounds,
            "settings": {"refine_points": self.refine_points, "loss": self.loss, "huber_px": self.huber_px},
            "points": {"num_observed": int(self.point_ids.size), "num_refined": int(self.point_refined.sum()),
                       "flatness_rms_m": flat_rms, "flatness_max_m": flat_max},
            "frames": per_frame,
            "skipped_frames": dict(self.skipped_frames),
        }


# ------------------------------------------------------------------------------ initialisation
def _as_table(observations: FeatureTable | Sequence[FeatureObservation]) -> FeatureTable:
    if isinstance(observations, FeatureTable):
        return observations
    return FeatureTable.from_observations(list(observations))


def _usable_rows(table: FeatureTable, num_features: int) -> np.ndarray:
    """Rows to calibrate with: finite positions, positive weight, not flagged ``FILTERED_OUT``."""
    bad_ids = (table.feature_id < 0) | (table.feature_id >= num_features)
    if np.any(bad_ids):
        raise ValueError(f"feature id {int(table.feature_id[bad_ids][0])} is not a feature of the pattern "
                         f"(ids 0..{num_features - 1})")
    keep = np.isfinite(table.x) & np.isfinite(table.y) & (table.weight > 0)
    return keep & ((table.flags & int(FeatureFlags.FILTERED_OUT)) == 0)


def _initialise(obj: list[np.ndarray], img: list[np.ndarray], image_size: tuple[int, int],
                outlier_sigmas: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``cv2.calibrateCamera`` on planar correspondences, rerun once without gross outliers.

    Returns intrinsics (9,), rvecs (F, 3), tvecs (F, 3) and the inlier mask of the
    concatenated observations (the outlier rule applied to the first fit).
    """
    def run(o: list[np.ndarray], i: list[np.ndarray]):
        _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            [a.astype(np.float32) for a in o], [a.astype(np.float32) for a in i], image_size, None, None)
        intr = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist.ravel()[:5]])
        return intr, np.array(rvecs).reshape(-1, 3), np.array(tvecs).reshape(-1, 3)

    try:
        intr, rvecs, tvecs = run(obj, img)
    except cv2.error as exc:
        raise CalibrationError(f"cv2.calibrateCamera failed on {len(obj)} frames: {str(exc).strip()}"
                               ) from exc
    errors = [np.linalg.norm(project_poses(intr, r, t, o).pixels - i, axis=1)
              for o, i, r, t in zip(obj, img, rvecs, tvecs, strict=True)]
    limit = robust_threshold(np.concatenate(errors), outlier_sigmas, 9 + 6 * len(obj))
    keep = [e <= limit for e in errors]
    if not all(k.all() for k in keep) and all(k.sum() >= 6 for k in keep):
        intr, rvecs, tvecs = run([o[k] for o, k in zip(obj, keep, strict=True)],
                                 [i[k] for i, k in zip(img, keep, strict=True)])
    return intr, rvecs, tvecs, np.concatenate(keep)


def _warm_start(start: Calibration, frames: list[str], table: FeatureTable
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """:func:`_initialise`'s outputs from ``start``: its intrinsics ``(9,)``, the poses ``(F, 3)``
    rvecs and tvecs of ``frames`` and the inlier mask of ``table``'s observations (an observation
    ``start`` did not fit counts as an inlier); None when ``start`` lacks a frame's pose."""
    if any(f not in start.poses for f in frames):
        return None
    c = start.camera
    intr = np.array([c.fx, c.fy, c.cx, c.cy, c.k1, c.k2, c.p1, c.p2, c.k3])
    rvecs = np.stack([start.poses[f].rvec for f in frames])
    tvecs = np.stack([start.poses[f].t for f in frames])
    known = dict(zip(zip(start.frame.tolist(), start.feature_id.tolist(), strict=True),
                     start.inlier.tolist(), strict=True))
    inlier = np.array([known.get(k, True) for k in zip(table.frame.tolist(), table.feature_id.tolist(),
                                                        strict=True)], dtype=bool)
    return intr, rvecs, tvecs, inlier


def calibrate_pinhole(points: Sequence[np.ndarray], pixels: Sequence[np.ndarray],
                      image_size: tuple[int, int]) -> tuple[BrownConrady, list[Pose]]:
    """A rough camera and poses from frames of any quality: one focal length, the principal point
    at the image centre, no distortion (``cv2.calibrateCamera`` with everything else fixed).

    For display (camera frustums before a calibration exists), not for measurement.

    Args:
        points: per frame, ``(N_f, 3)`` target points (m).
        pixels: per frame, ``(N_f, 2)`` observations (px, OpenCV convention).
        image_size: ``(width, height)`` px.
    Raises:
        CalibrationError: OpenCV's fit failed.
    """
    w, h = image_size
    f0 = float(max(w, h))
    K = np.array([[f0, 0.0, (w - 1) / 2.0], [0.0, f0, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO
             | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    try:
        _, K, _, rvecs, tvecs = cv2.calibrateCamera([np.asarray(p, np.float32) for p in points],
                                                    [np.asarray(p, np.float32) for p in pixels], (w, h), K,
                                                    np.zeros(5), flags=flags)
    except cv2.error as exc:
        raise CalibrationError(f"cv2.calibrateCamera failed on {len(points)} frames: {str(exc).strip()}"
                               ) from None
    camera = BrownConrady.from_matrix(K, None, w, h)
    return camera, [Pose.from_rvec_tvec(r.ravel(), t.ravel()) for r, t in zip(rvecs, tvecs, strict=True)]


def _usable_frames(table: FeatureTable, pattern: StarPattern, min_frames: int, min_features: int
                  ) -> tuple[FeatureTable, list[str], dict[str, int], np.ndarray]:
    """:func:`calibrate_sharp`'s observations: the usable rows (:func:`_usable_rows`) of the frames
    with at least ``min_features`` of them, sorted by frame and feature id. Returns them, the
    frames' names, the observation count of each frame left out, and each row's frame ``(N,)``.

    Raises:
        CalibrationError: fewer than ``min_frames`` usable frames.
        ValueError: a feature id outside the pattern or a repeated ``(frame, feature_id)``.
    """
    table = table.select(_usable_rows(table, pattern.num_features))
    names, counts = np.unique(table.frame, return_counts=True)
    usable = [str(n) for n, c in zip(names, counts, strict=True) if c >= min_features]
    skipped = {str(n): int(c) for n, c in zip(names, counts, strict=True) if c < min_features}
    if len(usable) < min_frames:
        listed = ", ".join(f"{n} ({c})" for n, c in list(skipped.items())[:10])
        more = f" and {len(skipped) - 10} more" if len(skipped) > 10 else ""
        raise CalibrationError(
            f"calibration needs at least {min_frames} sharp frames with >= {min_features} features each; "
            f"only {len(usable)} of {len(names)} frame(s) are usable"
            + (f"; too few features in: {listed}{more}" if skipped else ""))
    table = table.select(np.isin(table.frame, usable))
    frame_idx = np.searchsorted(np.array(usable), table.frame)
    order = np.lexsort((table.feature_id, frame_idx))
    table, frame_idx = table.select(order), frame_idx[order]
    key = frame_idx * pattern.num_features + table.feature_id
    if np.any(np.diff(key) == 0):
        dup = int(np.flatnonzero(np.diff(key) == 0)[0])
        raise ValueError(f"feature {int(table.feature_id[dup])} is observed twice in frame "
                         f"{table.frame[dup]!r}")
    return table, usable, skipped, frame_idx


def calibrate_sharp(observations: FeatureTable | Sequence[FeatureObservation], pattern: StarPattern,
                    image_size: tuple[int, int], refine_points: bool = True, loss: str = "huber",
                    huber_px: float = 1.0, min_frames: int = 5, *, min_features: int = 20,
                    outlier_sigmas: float = 5.0, point_sigma_m: float = 1e-3,
                    start: Calibration | None = None) -> Calibration:
    """Calibrate ``pi_d`` (Brown-Conrady) and the target points ``P`` from sharp-frame features.

    See the module docstring for the model, the gauge and the outlier rule.

    Args:
        observations: star-centre observations (px, OpenCV convention); rows flagged
            ``FILTERED_OUT``, with non-finite positions or with weight <= 0 are ignored, other
            weights are not used (every kept observation counts equally).
        pattern: the target; nominal points ``(fx L, fy L, 0)`` m by feature id.
        image_size: ``(width, height)`` px.
        refine_points: also estimate every observed point's ``(X, Y, Z)``.
        loss: ``"huber"`` (robust, per residual component, at ``huber_px``) or ``"linear"``.
        huber_px: Huber threshold (px).
        min_frames: fewest usable frames accepted.
        min_features: a frame is usable with at least this many observations.
        outlier_sigmas: an observation whose error exceeds this many robust sigmas is an outlier.
        point_sigma_m: standard deviation (m) of the weak prior holding points near nominal.
        start: a calibration of the same camera that saw every usable frame (e.g. of more frames):
            its intrinsics, poses and inlier set start the fit instead of OpenCV's
            (:func:`_initialise`), which saves the start and most outlier rounds. Frames it has not
            seen make the fit start cold.

    Returns:
        The :class:`Calibration`.

    Raises:
        CalibrationError: fewer than ``min_frames`` usable frames (names the count and the
            frames left out).
        ValueError: bad arguments, a feature id outside the pattern or a repeated
            ``(frame, feature_id)``.
    """
    if loss not in ("huber", "linear"):
        raise ValueError(f"loss must be 'huber' or 'linear', got {loss!r}")
    if not huber_px > 0 or not point_sigma_m > 0 or not outlier_sigmas > 0:
        raise ValueError(f"huber_px, point_sigma_m and outlier_sigmas must be positive, got {huber_px}, "
                         f"{point_sigma_m}, {outlier_sigmas}")
    if min_frames < 1 or min_features < 6:
        raise ValueError(f"need min_frames >= 1 and min_features >= 6, got {min_frames}, {min_features}")
    width, height = (int(v) for v in image_size)
    if width <= 0 or height <= 0:
        raise ValueError(f"image_size must be (width, height) > 0 px, got {tuple(image_size)}")
    table, usable, skipped, frame_idx = _usable_frames(_as_table(observations), pattern, min_frames,
                                                        min_features)
    nominal_all = pattern.points_3d()
    observed = np.column_stack([table.x, table.y])
    obs_points = nominal_all[table.feature_id]
    point_ids, point_idx = np.unique(table.feature_id, return_inverse=True)
    spans = list(itertools.pairwise(np.searchsorted(frame_idx, np.arange(len(usable) + 1))))
    warm = _warm_start(start, usable, table) if start is not None else None
    intr, rvecs, tvecs, inlier = warm or _initialise([obs_points[a:b] for a, b in spans],
                                                     [observed[a:b] for a, b in spans],
                                                     (width, height), outlier_sigmas)
    problem = ParametricProblem(frame_idx=frame_idx, point_idx=point_idx, observed=observed,
                       nominal=nominal_all[point_ids], fixed_points=obs_points, num_frames=len(usable),
                       refine_points=refine_points, point_sigma=point_sigma_m)
    params = np.concatenate([intr, np.column_stack([rvecs, tvecs]).ravel()]
                            + ([problem.nominal.ravel()] if refine_points else []))
    huber = huber_px if loss == "huber" else math.inf
    params, inlier, iterations, rounds = adjust(problem, params, inlier, huber, outlier_sigmas)
    intr, rotations, tvecs, pts = gauge_fixed(problem, params)
    points = np.full((pattern.num_features, 3), np.nan)
    points[point_ids] = pts
    refined = np.zeros(pattern.num_features, dtype=bool)
    refined[point_ids] = refine_points
    camera = BrownConrady(*intr, width=width, height=height)
    poses = {name: Pose(rotations[f], tvecs[f]) for f, name in enumerate(usable)}
    residuals = _residuals(camera, poses, points, table)
    inlier_errors = np.linalg.norm(residuals[inlier], axis=1)
    return Calibration(
        camera=camera, poses=poses, points=points, point_ids=point_ids, point_refined=refined,
        frame=table.frame, feature_id=table.feature_id, observed=observed, residuals=residuals,
        inlier=inlier, median_error=float(np.median(inlier_errors)),
        rms_error=float(np.sqrt(np.mean(inlier_errors**2))), num_frames=len(usable),
        num_observations=len(table), iterations=iterations, rounds=rounds, refine_points=refine_points,
        loss=loss, huber_px=float(huber_px), skipped_frames=skipped)


# --------------------------------------------------------------------------------- later stages
def reprojection_errors(calibration: Calibration,
                        observations: FeatureTable | Sequence[FeatureObservation]) -> np.ndarray:
    """``observed - pi_d(M_f, P_j)`` (px) of any observations, with the calibration's model.

    Args:
        calibration: camera, poses by frame name and points by feature id.
        observations: ``N`` observations.

    Returns:
        ``(N, 2)`` px; rows whose frame has no pose or whose point is unknown (NaN, or an id
        outside the points table) are NaN.
    """
    return _residuals(calibration.camera, calibration.poses, calibration.points, _as_table(observations))


def _residuals(camera: BrownConrady, poses: dict[str, Pose], points: np.ndarray, table: FeatureTable
               ) -> np.ndarray:
    """``observed - pi_d(M_f, P_j)`` ``(N, 2)`` px; NaN without a pose or a known point."""
    out = np.full((len(table), 2), np.nan)
    known = (table.feature_id >= 0) & (table.feature_id < len(points))
    for name, pose in poses.items():
        rows = np.flatnonzero((table.frame == name) & known)
        if rows.size:
            predicted = camera.project(pose.transform(points[table.feature_id[rows]]))
            out[rows] = np.column_stack([table.x[rows], table.y[rows]]) - predicted
    return out


def solve_pose(camera: BrownConrady, points: ArrayLike, obs_xy: ArrayLike, *,
               ransac_px: float = 3.0) -> Pose:
    """Robust pose ``M = [R | t]`` of one frame from 3D-2D correspondences.

    ``cv2.solvePnPRansac`` (SQPnP hypotheses, inliers within ``ransac_px``) followed by
    ``cv2.solvePnPRefineLM`` on the inliers, minimising ``sum |pi_d(M, P_i) - p_i|^2``.

    Args:
        camera: the calibrated camera.
        points: ``(N, 3)`` target points (m), ``N >= 4``.
        obs_xy: ``(N, 2)`` observed pixels (OpenCV convention).
        ransac_px: inlier threshold (px).

    Raises:
        ValueError: fewer than 4 correspondences, mismatched shapes, or no pose found.
    """
    pts = np.asarray(points, dtype=np.float64)
    xy = np.asarray(obs_xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or xy.shape != (len(pts), 2):
        raise ValueError(f"need points (N, 3) and obs_xy (N, 2), got {pts.shape} and {xy.shape}")
    finite = np.isfinite(pts).all(axis=1) & np.isfinite(xy).all(axis=1)
    pts, xy = pts[finite], xy[finite]
    if len(pts) < 4:
        raise ValueError(f"solve_pose needs at least 4 finite correspondences, got {len(pts)}")
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(pts, xy, camera.K, camera.dist, iterationsCount=200,
                                                 reprojectionError=float(ransac_px), confidence=0.999,
                                                 flags=cv2.SOLVEPNP_SQPNP)
    if not ok or inliers is None or len(inliers) < 4:
        raise ValueError(f"no pose found for {len(pts)} correspondences within {ransac_px} px")
    keep = inliers.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(pts[keep], xy[keep], camera.K, camera.dist, rvec, tvec)
    return Pose.from_rvec_tvec(rvec.ravel(), tvec.ravel())


# --------------------------------------------------------------------------------------- files
def save_calibration(folder: str | os.PathLike, calibration: Calibration) -> dict[str, Path]:
    """Write a calibration into ``folder`` (created if needed); every file atomically.

    Files: ``camera.yaml`` (OpenCV FileStorage) and ``camera.json`` (:mod:`blurcalib.camera.parametric`),
    ``points.csv`` (``feature_id, X, Y, Z`` m, ``refined`` 0/1; one row per pattern feature,
    ``nan`` for unobserved ones), ``residuals.csv`` (``frame, feature_id, x, y, dx, dy`` px,
    ``inlier`` 0/1) and ``calibration.json`` (:meth:`Calibration.to_dict`). Floats are written
    with ``repr`` and round-trip exactly (rotations through ``rvec`` to ~1e-15).

    Returns:
        Paths by kind: ``camera_yaml``, ``camera_json``, ``points``, ``residuals``, ``calibration``.
    """
    out = ensure_writable_dir(folder)
    paths = {"camera_yaml": out / CAMERA_YAML_FILE, "camera_json": out / CAMERA_JSON_FILE,
             "points": out / POINTS_FILE, "residuals": out / RESIDUALS_FILE,
             "calibration": out / CALIBRATION_FILE}
    save_camera_yaml(paths["camera_yaml"], calibration.camera)
    save_camera_json(paths["camera_json"], calibration.camera)
    point_rows = [(i, *map(repr, p.tolist()), int(r))
                  for i, (p, r) in enumerate(zip(calibration.points, calibration.point_refined, strict=True))]
    atomic_write_csv(paths["points"], _POINT_COLUMNS, point_rows)
    residual_rows = [(f, int(i), repr(o[0]), repr(o[1]), repr(r[0]), repr(r[1]), int(k))
                     for f, i, o, r, k in zip(calibration.frame.tolist(), calibration.feature_id,
                                              calibration.observed.tolist(), calibration.residuals.tolist(),
                                              calibration.inlier, strict=True)]
    atomic_write_csv(paths["residuals"], _RESIDUAL_COLUMNS, residual_rows)
    text = json.dumps(calibration.to_dict(), indent=2, allow_nan=False)
    atomic_write_text(paths["calibration"], text + "\n")
    return paths


def _parse(path: Path, values: list[str], kind: type, name: str) -> np.ndarray:
    try:
        return np.array([kind(v) for v in values], dtype=np.float64 if kind is float else np.int64)
    except ValueError as exc:
        raise CalibrationFileError(f"{path}: column {name!r}: {exc}") from None


def _pairs(path: Path, cols: dict[str, list[str]], names: tuple[str, str]) -> np.ndarray:
    """Two float columns as an ``(n, 2)`` array."""
    return np.column_stack([_parse(path, cols[c], float, c) for c in names]).reshape(-1, 2)


def load_calibration(folder: str | os.PathLike) -> Calibration:
    """Read a calibration written by :func:`save_calibration`.

    The camera comes from ``camera.json``; ``camera.yaml`` is not read.

    Raises:
        CalibrationFileError: a missing or malformed file; the message names it.
    """
    base = Path(folder)
    try:
        camera = load_camera_json(base / CAMERA_JSON_FILE)
    except CameraFileError as exc:
        raise CalibrationFileError(str(exc)) from None
    path = base / CALIBRATION_FILE
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
        settings = report["settings"]
        poses = {name: Pose.from_rvec_tvec(np.asarray(f["rvec"], float), np.asarray(f["tvec"], float))
                 for name, f in report["frames"].items()}
        scalars = {k: report[k] for k in ("median_error_px", "rms_error_px", "num_frames", "num_observations",
                                          "iterations", "rounds")}
        skipped = {str(k): int(v) for k, v in report["skipped_frames"].items()}
    except FileNotFoundError:
        raise CalibrationFileError(f"{path}: calibration file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CalibrationFileError(f"{path}: cannot read ({exc})") from None
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise CalibrationFileError(f"{path}: malformed calibration report ({exc!r})") from None
    pts_path = base / POINTS_FILE
    cols, _ = read_csv_columns(pts_path, _POINT_COLUMNS, CalibrationFileError, "calibration file")
    ids = _parse(pts_path, cols["feature_id"], int, "feature_id")
    if not np.array_equal(ids, np.arange(len(ids))):
        raise CalibrationFileError(f"{pts_path}: feature ids must run 0, 1, 2, ... in order")
    points = np.column_stack([_parse(pts_path, cols[c], float, c) for c in ("X", "Y", "Z")])
    res_path = base / RESIDUALS_FILE
    rcols, _ = read_csv_columns(res_path, _RESIDUAL_COLUMNS, CalibrationFileError, "calibration file")
    return Calibration(
        camera=camera, poses=poses, points=points.reshape(-1, 3),
        point_ids=np.flatnonzero(np.isfinite(points).all(axis=1)) if len(points) else np.zeros(0, np.int64),
        point_refined=_parse(pts_path, cols["refined"], int, "refined").astype(bool),
        frame=np.array(rcols["frame"], dtype=np.str_),
        feature_id=_parse(res_path, rcols["feature_id"], int, "feature_id"),
        observed=_pairs(res_path, rcols, ("x", "y")), residuals=_pairs(res_path, rcols, ("dx", "dy")),
        inlier=_parse(res_path, rcols["inlier"], int, "inlier").astype(bool),
        median_error=float(scalars["median_error_px"]), rms_error=float(scalars["rms_error_px"]),
        num_frames=int(scalars["num_frames"]), num_observations=int(scalars["num_observations"]),
        iterations=int(scalars["iterations"]), rounds=int(scalars["rounds"]),
        refine_points=bool(settings["refine_points"]), loss=str(settings["loss"]),
        huber_px=float(settings["huber_px"]), skipped_frames=skipped)
