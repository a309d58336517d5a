"""Parametric calibration of the sharp set, with the target's 3D points, for any model of the
parametric family (Brown-Conrady, OpenCV's rational model, Kannala-Brandt, the thin-prism
fisheye: :mod:`blurcalib.camera.family`) and any field of view.

The paper calibrates a parametric camera ``pi_d`` and the target's 3D points ``P`` from a small
sharp set; global alignment of the blurry frames then measures every observation against
``pi_d(M, P)``. This module does that calibration.

Model (``Brown_Conrady`` in the paper, OpenCV convention, see :mod:`blurcalib.camera.parametric`;
the other models: :mod:`blurcalib.camera.lens`)::

    p = pi_d(M_f, P_j) = K (d([R_f P_j + t_f]~), 1)
    d(x) = (1 + k1 r^2 + k2 r^4 + k3 r^6) x + (2 p1 x y + p2 (r^2 + 2 x^2), p1 (r^2 + 2 y^2) + 2 p2 x y)

for frame ``f`` with pose ``M_f = [R_f | t_f]`` (target -> camera, metres; ``R_f`` from the
Rodrigues vector ``rvec_f``) and target point ``P_j`` (metres) of feature ``j``.

Method (:func:`calibrate_sharp`):

1. **Initialisation** (:mod:`blurcalib.calib.parametric_start`). Brown-Conrady: by
   ``cv2.calibrateCamera`` on the planar correspondences ``(X, Y, 0) <-> (x, y)`` of every usable
   frame (``>= min_features`` observations): Zhang's method, whose start comes from the plane
   homographies ``H = K [r1 r2 t]`` (``eq:T``). If some observations are gross outliers of that
   fit (the rule below) it is run once more without them and the first adjustment round leaves
   them out. Kannala-Brandt (and OpenCV's fit when it fails or misses the observations by more
   than :data:`OPENCV_START_PX`): the undistorted equidistant camera whose focal length best
   explains each frame's plane homography in viewing directions, which works beyond 90 degrees
   off the axis. The rational model and the thin-prism fisheye start from the calibrated
   Kannala-Brandt camera converted (fitted to its rays).
2. **Robust bundle adjustment** by Levenberg-Marquardt with Huber weights
   (:mod:`blurcalib.calib.parametric_adjustment`: sparse analytic Jacobian, Marquardt's damping,
   the poses eliminated by the Schur complement and the rest solved directly) over the intrinsics
   (Brown-Conrady's ``(fx, fy, cx, cy, k1, k2, p1, p2, k3)``, or the model's), the poses
   ``(rvec_f, tvec_f)`` and, with
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
   (:func:`blurcalib.calib.parametric_adjustment.adjust`). An observation outside the model's
   valid field (a point behind a perspective model, say) is an outlier.

Residuals are reported as ``observed - predicted`` (the paper's ``p - pi_d(M, P)``) in pixels
(OpenCV pixel-centre convention).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from typing import cast

import cv2
import numpy as np

from blurcalib.calib.calibration import (
    CALIBRATION_FILE,
    CAMERA_JSON_FILE,
    CAMERA_YAML_FILE,
    PARAMETRIC_REF_FILE,
    POINTS_FILE,
    RESIDUALS_FILE,
    Calibration,
    CalibrationFileError,
    load_calibration,
    save_calibration,
)
from blurcalib.calib.parametric_adjustment import ParametricProblem, adjust, gauge_fixed
from blurcalib.calib.parametric_start import Start, converted_start, equidistant_start, opencv_start
from blurcalib.calib.pnp import solve_pose
from blurcalib.camera.brown_conrady import BrownConradyCamera
from blurcalib.camera.family import as_family, model_class
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.geometry.pose import Pose
from blurcalib.io.results import FeatureFlags, FeatureObservation, FeatureTable
from blurcalib.target.pattern import StarPattern

__all__ = [
    "CALIBRATION_FILE",
    "CAMERA_JSON_FILE",
    "CAMERA_YAML_FILE",
    "OPENCV_START_PX",
    "PARAMETRIC_REF_FILE",
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

OPENCV_START_PX = 2.0
"""OpenCV's Brown-Conrady start whose median error exceeds this (px) is replaced by the
Kannala-Brandt route (a lens Brown-Conrady cannot describe, or points beyond 90 degrees)."""


class CalibrationError(ValueError):
    """The observations cannot be calibrated (too few usable frames); the message says why."""


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
    return cast(np.ndarray, keep & ((table.flags & int(FeatureFlags.FILTERED_OUT)) == 0))


def _warm_start(start: Calibration, frames: list[str], table: FeatureTable, model: type[ParametricCamera],
                obj: list[np.ndarray], img: list[np.ndarray], outlier_sigmas: float) -> Start | None:
    """The start from ``start``: its intrinsics (converted when ``model`` is another:
    :func:`blurcalib.calib.parametric_start.converted_start`), the poses of ``frames`` and its
    inlier set on ``table``'s observations (an observation ``start`` did not fit counts as an
    inlier); None when ``start`` lacks a frame's pose."""
    if any(f not in start.poses for f in frames):
        return None
    camera = as_family(start.camera)
    rvecs = np.stack([start.poses[f].rvec for f in frames])
    tvecs = np.stack([start.poses[f].t for f in frames])
    if type(camera) is not model:
        return converted_start(camera, rvecs, tvecs, model, obj, img, outlier_sigmas)
    known = dict(zip(zip(start.frame.tolist(), start.feature_id.tolist(), strict=True),
                     start.inlier.tolist(), strict=True))
    inlier = np.array([known.get(k, True) for k in zip(table.frame.tolist(), table.feature_id.tolist(),
                                                        strict=True)], dtype=bool)
    return Start(camera, rvecs, tvecs, inlier, math.nan)


def _cold_start(model: type[ParametricCamera], obj: list[np.ndarray], img: list[np.ndarray],
                size: tuple[int, int], outlier_sigmas: float, kannala_brandt: Callable[[], Calibration],
                frames: list[str]) -> Start:
    """The start without a calibration to start from (module docstring, step 1): OpenCV's for
    Brown-Conrady when it fits within :data:`OPENCV_START_PX`, the equidistant scan for
    Kannala-Brandt, else the calibrated Kannala-Brandt camera (``kannala_brandt()``) converted."""
    if model is BrownConradyCamera:
        start = opencv_start(obj, img, size, outlier_sigmas)
        if start is not None and start.median_px <= OPENCV_START_PX:
            return start
    if model is KannalaBrandtCamera:
        return equidistant_start(obj, img, size, outlier_sigmas)
    fisheye = kannala_brandt()
    camera = as_family(fisheye.camera)
    rvecs = np.stack([fisheye.poses[f].rvec for f in frames])
    tvecs = np.stack([fisheye.poses[f].t for f in frames])
    return converted_start(camera, rvecs, tvecs, model, obj, img, outlier_sigmas)


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
                    start: Calibration | None = None, model: str | None = None) -> Calibration:
    """Calibrate ``pi_d`` (a model of the parametric family) and the target points ``P`` from
    sharp-frame features.

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
            its intrinsics (converted to ``model`` when it is another), poses and inlier set start
            the fit instead of the cold start (module docstring), which saves the start and most
            outlier rounds. Frames it has not seen make the fit start cold.
        model: the model's name (:data:`blurcalib.camera.family.MODELS`); None: ``start``'s, or
            ``Brown_Conrady`` without one.

    Returns:
        The :class:`Calibration`.

    Raises:
        CalibrationError: fewer than ``min_frames`` usable frames (names the count and the
            frames left out), or no start of the model explains the observations.
        ValueError: bad arguments, a feature id outside the pattern or a repeated
            ``(frame, feature_id)``.
    """
    name = model if model is not None else start.model if start is not None else BrownConradyCamera.MODEL
    cls = model_class(name)
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
    obj, img = [obs_points[a:b] for a, b in spans], [observed[a:b] for a, b in spans]
    warm = (_warm_start(start, usable, table, cls, obj, img, outlier_sigmas) if start is not None
            else None)

    def kannala_brandt() -> Calibration:
        return calibrate_sharp(table, pattern, (width, height), False, loss, huber_px, 1,
                               min_features=min_features, outlier_sigmas=outlier_sigmas,
                               model=KannalaBrandtCamera.MODEL)

    first = warm or _cold_start(cls, obj, img, (width, height), outlier_sigmas, kannala_brandt, usable)
    problem = ParametricProblem(camera=first.camera, frame_idx=frame_idx, point_idx=point_idx,
                                observed=observed, nominal=nominal_all[point_ids], fixed_points=obs_points,
                                num_frames=len(usable), refine_points=refine_points,
                                point_sigma=point_sigma_m)
    params = np.concatenate([first.camera.params, np.column_stack([first.rvecs, first.tvecs]).ravel()]
                            + ([problem.nominal.ravel()] if refine_points else []))
    huber = huber_px if loss == "huber" else math.inf
    if first.inlier.sum() < 6 * len(usable):
        raise CalibrationError(f"no {name} camera explains the observations of the {len(usable)} frames "
                               f"(start error {first.median_px:.3g} px median)")
    params, inlier, iterations, rounds = adjust(problem, params, first.inlier, huber, outlier_sigmas)
    intr, rotations, tvecs, pts = gauge_fixed(problem, params)
    points = np.full((pattern.num_features, 3), np.nan)
    points[point_ids] = pts
    refined = np.zeros(pattern.num_features, dtype=bool)
    refined[point_ids] = refine_points
    try:
        fitted = first.camera.with_params(intr)
    except ValueError as exc:  # a focal length the fit drove to 0 or below
        raise CalibrationError(f"the {name} fit diverged ({exc})") from None
    camera = fitted.to_brown_conrady() if isinstance(fitted, BrownConradyCamera) else fitted
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


def _residuals(camera: BrownConrady | ParametricCamera, poses: dict[str, Pose], points: np.ndarray,
               table: FeatureTable) -> np.ndarray:
    """``observed - pi_d(M_f, P_j)`` ``(N, 2)`` px; NaN without a pose or a known point."""
    out = np.full((len(table), 2), np.nan)
    known = (table.feature_id >= 0) & (table.feature_id < len(points))
    for name, pose in poses.items():
        rows = np.flatnonzero((table.frame == name) & known)
        if rows.size:
            predicted = camera.project(pose.transform(points[table.feature_id[rows]]))
            out[rows] = np.column_stack([table.x[rows], table.y[rows]]) - predicted
    return out

