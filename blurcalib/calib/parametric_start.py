"""Where the parametric calibration of :mod:`blurcalib.calib.sharp` starts, for any model of the
family and any field of view.

* :func:`opencv_start`: Brown-Conrady by ``cv2.calibrateCamera`` (Zhang's method from the plane
  homographies ``H = K [r1 r2 t]``, ``eq:T``), once more without gross outliers;
* :func:`equidistant_start`: a Kannala-Brandt camera without distortion (``r = f theta``) whose
  principal point is the image centre and whose focal length is the best of a scan: for each
  focal length the observations' rays give each frame's pose by the plane homography in
  directions (:func:`blurcalib.calib.pnp.plane_homography`, any angle off the axis), and the
  median reprojection error over all frames scores it. The scan covers half fields of view of
  the image's long side from 10 to 115 degrees, then refines around the best;
* :func:`converted_start`: a calibrated camera of one model as a camera of another: the other
  model fitted to the first one's rays over the observed part of the image
  (:func:`blurcalib.camera.fit.fit_rays`, a rotation absorbed by the poses).

Each gives the intrinsics, every frame's pose ``(rvec, tvec)`` (rad, m) and which observations
start as inliers (those within :func:`blurcalib.calib.parametric_adjustment.robust_threshold` of
the start's errors). Pixels follow OpenCV (top-left pixel centre at ``(0, 0)``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from blurcalib.calib.parametric_adjustment import robust_threshold
from blurcalib.calib.pnp import homography_pose, plane_homography
from blurcalib.camera.brown_conrady import BrownConradyCamera
from blurcalib.camera.fit import fit_rays
from blurcalib.camera.kannala_brandt import KannalaBrandtCamera
from blurcalib.camera.lens import ParametricCamera, project_poses_camera
from blurcalib.camera.parametric import rodrigues_jacobian

__all__ = ["Start", "converted_start", "equidistant_start", "opencv_start", "start_errors"]

SCAN_HALF_FIELDS_DEG = (10.0, 115.0)
"""Half fields of view of the image's long side that :func:`equidistant_start` scans."""
SCAN_STEPS = 36
MIN_FRAME_POINTS = 6
"""Fewest rays of a frame for its pose in :func:`equidistant_start`."""


@dataclass(frozen=True, eq=False)
class Start:
    """A start of the parametric calibration.

    Attributes:
        camera: the model and its start intrinsics.
        rvecs, tvecs: ``(F, 3)`` each frame's pose (target -> camera; rad, m).
        inlier: ``(N,)`` the observations the first fit uses (concatenated over the frames).
        median_px: median start error over all observations (``inf`` counted where a point has
            no projection).
    """

    camera: ParametricCamera
    rvecs: np.ndarray
    tvecs: np.ndarray
    inlier: np.ndarray
    median_px: float


def start_errors(camera: ParametricCamera, rvecs: np.ndarray, tvecs: np.ndarray, obj: list[np.ndarray],
                 img: list[np.ndarray]) -> np.ndarray:
    """``(N,)`` px reprojection errors of every frame's observations (concatenated), ``inf`` where
    the point lies outside the camera's valid field."""
    out = []
    for o, i, r, t in zip(obj, img, rvecs, tvecs, strict=True):
        R = rodrigues_jacobian(r)[0][0]
        cam = o @ R.T + t
        e = np.linalg.norm(project_poses_camera(camera, r[None], t[None], o).pixels - i, axis=1)
        out.append(np.where(camera.valid_directions(cam) & np.isfinite(e), e, np.inf))
    return np.concatenate(out)


def _finish(camera: ParametricCamera, rvecs: np.ndarray, tvecs: np.ndarray, obj: list[np.ndarray],
            img: list[np.ndarray], outlier_sigmas: float) -> Start:
    """The :class:`Start` of a camera and poses: inliers by the robust threshold of its errors."""
    errors = start_errors(camera, rvecs, tvecs, obj, img)
    finite = np.isfinite(errors)
    limit = robust_threshold(errors[finite], outlier_sigmas, len(camera.params) + 6 * len(obj)) \
        if finite.any() else 0.0
    return Start(camera, rvecs, tvecs, errors <= limit, float(np.median(errors)))


def opencv_start(obj: list[np.ndarray], img: list[np.ndarray], image_size: tuple[int, int],
                 outlier_sigmas: float) -> Start | None:
    """Brown-Conrady by ``cv2.calibrateCamera`` on planar correspondences (per frame ``(N_f, 3)``
    m and ``(N_f, 2)`` px), rerun once without the gross outliers of the first fit; None when
    OpenCV fails. The inliers are the outlier rule applied to the first fit."""
    def run(o: list[np.ndarray], i: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            [a.astype(np.float32) for a in o], [a.astype(np.float32) for a in i], image_size, None, None)
        intr = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist.ravel()[:5]])
        return intr, np.array(rvecs).reshape(-1, 3), np.array(tvecs).reshape(-1, 3)

    width, height = image_size
    try:
        intr, rvecs, tvecs = run(obj, img)
        first = BrownConradyCamera(intr, width, height)
    except (cv2.error, ValueError):  # OpenCV's failure, or a camera it cannot describe (f <= 0)
        return None
    errors = [np.linalg.norm(project_poses_camera(first, r[None], t[None], o).pixels - i, axis=1)
              for o, i, r, t in zip(obj, img, rvecs, tvecs, strict=True)]
    everything = np.concatenate(errors)
    if not np.isfinite(everything).all():
        return None
    limit = robust_threshold(everything, outlier_sigmas, 9 + 6 * len(obj))
    keep = [e <= limit for e in errors]
    if not all(k.all() for k in keep) and all(k.sum() >= 6 for k in keep):
        try:
            intr, rvecs, tvecs = run([o[k] for o, k in zip(obj, keep, strict=True)],
                                     [i[k] for i, k in zip(img, keep, strict=True)])
            first = BrownConradyCamera(intr, width, height)
        except (cv2.error, ValueError):
            return None
    median = float(np.median(start_errors(first, rvecs, tvecs, obj, img)))
    return Start(first, rvecs, tvecs, np.concatenate(keep), median)


def _scan_score(f: float, centre: np.ndarray, obj: list[np.ndarray], img: list[np.ndarray],
                size: tuple[int, int]) -> tuple[float, np.ndarray, np.ndarray]:
    """Median error of the undistorted equidistant camera of focal length ``f`` with each frame's
    pose from its rays' plane homography, and those poses."""
    camera = KannalaBrandtCamera(np.r_[f, f, centre, np.zeros(4)], *size)
    rvecs, tvecs, errors = [], [], []
    for o, i in zip(obj, img, strict=True):
        rays = camera.unproject(i)
        seen = np.all(np.isfinite(rays), axis=1)
        pose = (homography_pose(plane_homography(rays[seen], o[seen]))
                if seen.sum() >= MIN_FRAME_POINTS else None)
        if pose is None:
            rvecs.append(np.zeros(3))
            tvecs.append(np.array([0.0, 0.0, 1.0]))
            errors.append(np.full(len(i), np.inf))
            continue
        rvecs.append(pose.rvec)
        tvecs.append(pose.t)
        errors.append(start_errors(camera, pose.rvec[None], pose.t[None], [o], [i]))
    return float(np.median(np.concatenate(errors))), np.array(rvecs), np.array(tvecs)


def equidistant_start(obj: list[np.ndarray], img: list[np.ndarray], image_size: tuple[int, int],
                      outlier_sigmas: float) -> Start:
    """The undistorted equidistant camera of the best focal length and each frame's pose (module
    docstring): a start for a lens of any field of view."""
    width, height = image_size
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    half = max(width, height) / 2.0
    lo, hi = (math.radians(a) for a in SCAN_HALF_FIELDS_DEG)
    focal = half / np.geomspace(lo, hi, SCAN_STEPS)
    scores = [_scan_score(float(f), centre, obj, img, image_size)[0] for f in focal]
    best = int(np.argmin(scores))
    ratio = (hi / lo) ** (1.0 / (SCAN_STEPS - 1))
    finer = focal[best] * ratio ** np.linspace(-1.0, 1.0, 9)
    results = [_scan_score(float(f), centre, obj, img, image_size) for f in finer]
    k = int(np.argmin([r[0] for r in results]))
    camera = KannalaBrandtCamera(np.r_[finer[k], finer[k], centre, np.zeros(4)], width, height)
    return _finish(camera, results[k][1], results[k][2], obj, img, outlier_sigmas)


def converted_start(camera: ParametricCamera, rvecs: np.ndarray, tvecs: np.ndarray,
                    model: type[ParametricCamera], obj: list[np.ndarray], img: list[np.ndarray],
                    outlier_sigmas: float) -> Start:
    """``camera`` (and its poses) as a camera of ``model``: the model fitted to ``camera``'s rays on
    a lattice over the observations' bounding box (:func:`blurcalib.camera.fit.fit_rays`), the
    fit's rotation ``Q`` moved into the poses (``R <- Q R``, ``t <- Q t``). A model that holds
    ``camera``'s own coefficients (Kannala-Brandt in the thin-prism fisheye, Brown-Conrady in the
    rational model) starts from them."""
    width, height = camera.width, camera.height
    px = np.concatenate(img)
    lo, hi = px.min(axis=0), px.max(axis=0)
    xs, ys = np.linspace(lo[0], hi[0], 33), np.linspace(lo[1], hi[1], 19)
    lattice = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    rays = camera.unproject(lattice)
    seed = _embedded(camera, model)
    fit = fit_rays(model, lattice, rays, width, height, start=seed)
    R = rodrigues_jacobian(rvecs)[0]
    turned = np.einsum("ij,fjk->fik", fit.rotation, R)
    new_rvecs = np.stack([cv2.Rodrigues(np.ascontiguousarray(r))[0].ravel() for r in turned])
    return _finish(fit.camera, new_rvecs, tvecs @ fit.rotation.T, obj, img, outlier_sigmas)


def _embedded(camera: ParametricCamera, model: type[ParametricCamera]) -> ParametricCamera | None:
    """``camera`` as a camera of ``model`` when ``model`` holds it exactly (its coefficients are
    among ``model``'s and the base point is the same), else None."""
    probe = model(np.r_[camera.params[:4], np.zeros(len(model.PARAM_NAMES) - 4)], camera.width, camera.height)
    if probe.angular != camera.angular or not set(camera.PARAM_NAMES) <= set(model.PARAM_NAMES):
        return None
    kernel = dict(zip(camera.PARAM_NAMES[4:], camera.KERNEL_INDEX, strict=True))
    if any(model.KERNEL_INDEX[model.PARAM_NAMES.index(n) - 4] != k for n, k in kernel.items()):
        return None
    values = camera.named()
    return probe.with_params([values.get(n, 0.0) for n in model.PARAM_NAMES])
