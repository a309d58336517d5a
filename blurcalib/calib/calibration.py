"""A parametric calibration of the sharp set (:class:`Calibration`: camera, poses, refined target
points, residuals) and its folder of files (:func:`save_calibration`, :func:`load_calibration`).

:func:`blurcalib.calib.sharp.calibrate_sharp` makes it. Pixels follow OpenCV (top-left pixel centre
at ``(0, 0)``); poses map target to camera, ``X_cam = R X + t`` (m).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from blurcalib.camera.brown_conrady import BrownConradyCamera
from blurcalib.camera.family import as_family, camera_from_dict
from blurcalib.camera.files import write_parametric_yaml
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.opencv_files import write_opencv_camera
from blurcalib.camera.parametric import BrownConrady, CameraFileError, save_camera_json, save_camera_yaml
from blurcalib.camera.storage import read_text
from blurcalib.geometry.pose import Pose
from blurcalib.io.atomic import atomic_write_csv, atomic_write_text, ensure_writable_dir, read_csv_columns

__all__ = [
    "CALIBRATION_FILE",
    "CAMERA_JSON_FILE",
    "CAMERA_YAML_FILE",
    "PARAMETRIC_REF_FILE",
    "POINTS_FILE",
    "RESIDUALS_FILE",
    "Calibration",
    "CalibrationFileError",
    "load_calibration",
    "save_calibration",
]

CAMERA_YAML_FILE = "camera.yaml"
CAMERA_JSON_FILE = "camera.json"
POINTS_FILE = "points.csv"
RESIDUALS_FILE = "residuals.csv"
CALIBRATION_FILE = "calibration.json"
PARAMETRIC_REF_FILE = "parametric_intrinsics0.yaml"
"""The parametric camera in the reference tool's format
(:func:`blurcalib.camera.files.write_parametric_yaml`)."""
_POINT_COLUMNS = ("feature_id", "X", "Y", "Z", "refined")
_RESIDUAL_COLUMNS = ("frame", "feature_id", "x", "y", "dx", "dy", "inlier")


class CalibrationFileError(ValueError):
    """A calibration folder's file is missing or malformed; the message names the file."""


@dataclass(eq=False)
class Calibration:
    """A calibrated parametric camera, the sharp frames' poses and the refined target points.

    Attributes:
        camera: the calibrated camera ``pi_d``: a :class:`BrownConrady` for ``Brown_Conrady``,
            else the family's camera of its model (:mod:`blurcalib.camera.lens`).
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

    camera: BrownConrady | ParametricCamera
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
    def model(self) -> str:
        """The camera model's name (``Brown_Conrady``, ``rational``, ``Kannala_Brandt``,
        ``thin_prism_fisheye``)."""
        return as_family(self.camera).MODEL

    @property
    def errors(self) -> np.ndarray:
        """``(N,)`` px, reprojection error norms ``|residual|``."""
        return cast(np.ndarray, np.linalg.norm(self.residuals, axis=1))

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
            "model": self.model,
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

def save_calibration(folder: str | os.PathLike[str], calibration: Calibration) -> dict[str, Path]:
    """Write a calibration into ``folder`` (created if needed); every file atomically.

    Files: ``camera.yaml`` (OpenCV FileStorage: :func:`blurcalib.camera.parametric.save_camera_yaml`
    for Brown-Conrady, :func:`blurcalib.camera.opencv_files.write_opencv_camera` for the other
    models OpenCV has; none for the thin-prism fisheye), ``parametric_intrinsics0.yaml`` (the
    reference tool's, :func:`blurcalib.camera.files.write_parametric_yaml`), ``camera.json`` (the
    camera's ``to_dict``), ``points.csv`` (``feature_id, X, Y, Z`` m, ``refined`` 0/1; one row per
    pattern feature, ``nan`` for unobserved ones), ``residuals.csv`` (``frame, feature_id, x, y, dx, dy`` px,
    ``inlier`` 0/1) and ``calibration.json`` (:meth:`Calibration.to_dict`). Floats are written
    with ``repr`` and round-trip exactly (rotations through ``rvec`` to ~1e-15).

    Returns:
        Paths by kind: ``camera_yaml`` (not for the thin-prism fisheye), ``parametric_ref``,
        ``camera_json``, ``points``, ``residuals``, ``calibration``.
    """
    out = ensure_writable_dir(folder)
    camera = calibration.camera
    paths = {"camera_yaml": out / CAMERA_YAML_FILE, "parametric_ref": out / PARAMETRIC_REF_FILE,
             "camera_json": out / CAMERA_JSON_FILE, "points": out / POINTS_FILE,
             "residuals": out / RESIDUALS_FILE, "calibration": out / CALIBRATION_FILE}
    if isinstance(camera, BrownConrady):
        save_camera_yaml(paths["camera_yaml"], camera)
    elif camera.OPENCV_DISTORTION is not None:
        write_opencv_camera(paths["camera_yaml"], camera)
    else:
        del paths["camera_yaml"]
        (out / CAMERA_YAML_FILE).unlink(missing_ok=True)
    write_parametric_yaml(paths["parametric_ref"], as_family(camera))
    save_camera_json(paths["camera_json"], camera)
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


def _load_camera(path: Path) -> BrownConrady | ParametricCamera:
    """The camera of ``camera.json``: a :class:`BrownConrady` for Brown-Conrady, else the family's."""
    try:
        data = json.loads(read_text(path))
        camera = camera_from_dict(data)
    except CameraFileError as exc:
        raise CalibrationFileError(str(exc)) from None
    except (json.JSONDecodeError, ValueError, TypeError) as exc:
        raise CalibrationFileError(f"camera file {str(path)!r} is invalid: {exc}") from None
    return camera.to_brown_conrady() if isinstance(camera, BrownConradyCamera) else camera


def load_calibration(folder: str | os.PathLike[str]) -> Calibration:
    """Read a calibration written by :func:`save_calibration`.

    The camera comes from ``camera.json``; ``camera.yaml`` is not read.

    Raises:
        CalibrationFileError: a missing or malformed file; the message names it.
    """
    base = Path(folder)
    camera = _load_camera(base / CAMERA_JSON_FILE)
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
