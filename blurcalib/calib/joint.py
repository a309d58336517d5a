"""Generic calibration of a feature set: sharp frames plus, optionally, blurry frames.

:func:`calibrate_generic` turns the pipeline's features and its parametric (Brown-Conrady)
calibration into a generic camera (:mod:`blurcalib.camera.generic`) fitted by
:func:`blurcalib.calib.bundle.bundle_adjust`:

* the calibrated area is the integer bounding box of every used feature (pixel-corner), the grid
  ``cell_px`` cells; the initial grid reproduces the parametric camera's rays;
* target points: the nominal ``(fx L, fy L, 0)`` by default, fixed. The parametric
  calibration's refined points absorb part of the Brown-Conrady model's misfit (its 1 mm
  out-of-plane freedom bends the target to fit the lens), and a generic fit held to them inherits
  that bias: on the demo's simulated dataset (a flat target, a lens 0.3 px off Brown-Conrady) the
  generic camera of sharp and blurry frames is 0.099 px (median) from the true camera with the
  refined points and 0.014 px with the nominal ones. ``points="parametric"`` keeps the refined
  points (for a target known not to be flat);
* sharp frames start from the parametric poses, other frames from a PnP with the parametric camera;
* ``route="joint"`` (default): every blurry frame gets a free image shift ``s_f`` (the
  deconvolution's translational ambiguity) with a weak prior, so no orientation filter is needed;
  ``route="aligned"``: the paper's route, the blurry features are taken as already aligned
  (:func:`blurcalib.calib.alignment.align_global`) and held fixed (no shift).

Rows flagged ``FILTERED_OUT`` or with zero weight are not used; ``weight`` weights the rest.
:func:`save_generic_calibration` writes the reference tool's ``intrinsics0.yaml``, the poses,
an undistortion map, the coverage map and the generic-minus-parametric difference image.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from blurcalib.calib.bundle import BundleResult, BundleSettings, bundle_adjust
from blurcalib.calib.frame_block import RollingRows
from blurcalib.calib.sharp import Calibration, solve_pose
from blurcalib.calib.undistortion import (
    UNDISTORT,
    UNDISTORTION_FILE,
    undistortion_output,
    write_undistortion_map,
)
from blurcalib.camera.files import write_generic_yaml
from blurcalib.camera.generic import (
    DEFAULT_CELL_PX,
    CentralGeneric,
    best_fit_rotation,
    calibrated_area,
    check_grid_size,
    fit_to_rays,
)
from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.camera.remap import OutputProjection
from blurcalib.camera.shutter import row_time
from blurcalib.geometry.pose import Pose
from blurcalib.io.atomic import atomic_path, atomic_write_csv, ensure_writable_dir
from blurcalib.io.results import FeatureFlags, FeatureTable
from blurcalib.target.pattern import StarPattern

__all__ = [
    "GenericCalibration",
    "JointSettings",
    "calibrate_generic",
    "difference_field",
    "generic_report",
    "save_generic_calibration",
]

ROUTES = ("joint", "aligned")
POINTS = ("nominal", "parametric")
INTRINSICS_FILE = "intrinsics0.yaml"
POSES_FILE = "generic_poses.csv"
COVERAGE_FILE = "generic_coverage.png"
DIFFERENCE_FILE = "generic_minus_parametric.png"


@dataclass(frozen=True)
class JointSettings:
    """Options of :func:`calibrate_generic`.

    Attributes:
        cell_px: grid cell length (px).
        route: ``"joint"`` (free per-frame shifts of blurry frames) or ``"aligned"``.
        points: target points of the fit: ``"nominal"`` (flat, the pattern's) or
            ``"parametric"`` (the sharp-set calibration's refined points); see the module
            docstring.
        min_features: frames with fewer usable features are left out.
        bundle: the bundle adjustment's options.
        undistort: the projection of the undistortion map
            (:func:`blurcalib.calib.undistortion.undistortion_output`): ``"auto"``, ``"pinhole"``,
            ``"latlong"`` or ``"stereographic"``.
    """

    cell_px: float = DEFAULT_CELL_PX
    route: str = "joint"
    points: str = "nominal"
    min_features: int = 8
    bundle: BundleSettings = field(default_factory=BundleSettings)
    undistort: str = "auto"

    def __post_init__(self) -> None:
        if self.undistort not in UNDISTORT:
            raise ValueError(f"undistort must be one of {UNDISTORT}, got {self.undistort!r}")
        if self.route not in ROUTES:
            raise ValueError(f"route must be one of {ROUTES}, got {self.route!r}")
        if self.points not in POINTS:
            raise ValueError(f"points must be one of {POINTS}, got {self.points!r}")
        if not self.cell_px > 0:
            raise ValueError(f"cell_px must be positive, got {self.cell_px}")


@dataclass(eq=False)
class GenericCalibration:
    """A generic calibration and its fit.

    Attributes:
        model: the generic camera.
        parametric: the parametric camera it started from.
        poses: frame -> pose (target -> camera) in the generic model's frame.
        shifts: frame -> ``(2,)`` px estimated image shift (blurry frames, joint route).
        frames: names of the frames used, in the bundle adjustment's order.
        blurry_frames: names of the blurry frames used.
        frame, feature_id: ``(N,)`` the used observations.
        points: ``(N, 3)`` m, the target points they were fitted with; weight ``(N,)`` theirs.
        observed, residuals: ``(N, 2)`` px (residual = observed - projection - shift).
        inlier: ``(N,)`` bool.
        median_error, rms_error: px over inliers; ``sharp_median_error``, ``blurry_median_error``
            the same per kind (NaN without that kind).
        skipped_frames: frame -> usable feature count of frames left out.
        route: the route used.
        bundle: the bundle adjustment's full result (coverage, warnings, timing).
        rolling: frame -> ``(12,)`` rolling parameters ``theta`` (rad, m per unit row ``y`` and
            ``y^2``, :mod:`blurcalib.calib.bundle`) of the blurry frames, when the rolling shutter
            was fitted with the camera (``rolling_twist_sigma``); else empty.
    """

    model: CentralGeneric
    parametric: BrownConrady | ParametricCamera
    poses: dict[str, Pose]
    shifts: dict[str, np.ndarray]
    frames: list[str]
    blurry_frames: list[str]
    frame: np.ndarray = field(repr=False)
    feature_id: np.ndarray = field(repr=False)
    points: np.ndarray = field(repr=False)
    weight: np.ndarray = field(repr=False)
    observed: np.ndarray = field(repr=False)
    residuals: np.ndarray = field(repr=False)
    inlier: np.ndarray = field(repr=False)
    median_error: float
    rms_error: float
    sharp_median_error: float
    blurry_median_error: float
    skipped_frames: dict[str, int]
    route: str
    bundle: BundleResult = field(repr=False)
    rolling: dict[str, np.ndarray] = field(default_factory=dict, repr=False)


def _usable(table: FeatureTable) -> FeatureTable:
    keep = ((table.flags & int(FeatureFlags.FILTERED_OUT)) == 0) & (table.weight > 0)
    keep &= np.isfinite(table.x) & np.isfinite(table.y)
    return table.select(keep)


def calibrate_generic(sharp_features: FeatureTable, blurry_features: FeatureTable | None,
                      parametric: Calibration, pattern: StarPattern, size: tuple[int, int],
                      settings: JointSettings | None = None, rolling_twist_sigma: float | None = None
                      ) -> GenericCalibration:
    """Fit the generic camera to the sharp and (optionally) blurry features (module docstring).

    Args:
        sharp_features: the sharp frames' features.
        blurry_features: the blurry frames' features (raw or globally aligned), or None.
        parametric: the sharp-set calibration (camera, poses, refined points): the initial camera
            and the sharp frames' initial poses.
        pattern: the target.
        size: ``(width, height)`` of the images (px).
        settings: options.
        rolling_twist_sigma: when given, every blurry frame also gets its rolling-shutter
            parameters, fitted with the camera (:class:`blurcalib.calib.frame_block.RollingRows`, this
            their prior in rad and times the frame's distance in m; rows of ``size[1]``).

    Raises:
        ValueError: no frame with enough usable features.
    """
    settings = settings or JointSettings()
    width, height = size
    camera = parametric.camera
    tables = [("sharp", _usable(sharp_features))]
    if blurry_features is not None:
        tables.append(("blurry", _usable(blurry_features)))
    nominal = pattern.points_3d()
    frames: list[str] = []
    kinds: list[str] = []
    poses: list[Pose] = []
    rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    skipped: dict[str, int] = {}
    for kind, table in tables:
        for name in dict.fromkeys(table.frame.tolist()):
            sel = table.frame == name
            ids = table.feature_id[sel]
            if len(ids) < settings.min_features:
                skipped[name] = len(ids)
                continue
            refined = settings.points == "parametric" and len(parametric.points) == len(nominal)
            pts = parametric.points[ids] if refined else nominal[ids]
            pts = np.where(np.isfinite(pts), pts, nominal[ids])
            obs = np.column_stack([table.x[sel], table.y[sel]])
            if kind == "sharp" and name in parametric.poses:
                pose = parametric.poses[name]
            else:
                try:
                    pose = solve_pose(camera, pts, obs, ransac_px=20.0)
                except (ValueError, cv2.error):  # no pose, or OpenCV's SQPnP on a degenerate sample
                    skipped[name] = len(ids)
                    continue
            rows.append((np.full(len(ids), len(frames)), ids, pts, obs, table.weight[sel]))
            frames.append(name)
            kinds.append(kind)
            poses.append(pose)
    if not frames:
        raise ValueError(f"no frame has {settings.min_features} or more usable features")
    index, ids, pts, obs, weight = (np.concatenate(c) for c in zip(*rows, strict=True))
    area = calibrated_area(obs, width, height)
    check_grid_size(area[2] + 1 - area[0], area[3] + 1 - area[1], settings.cell_px)
    initial = fit_to_rays(camera.pixel_to_ray, width, height, area=area, cell_px=settings.cell_px)
    shift_free = np.array([k == "blurry" and settings.route == "joint" for k in kinds])
    moving = np.array([k == "blurry" for k in kinds])
    rolling = None if rolling_twist_sigma is None else \
        RollingRows(row_time(obs[:, 1], height, 1.0), moving, rolling_twist_sigma)
    res = bundle_adjust(initial, poses, index, pts, obs, weights=weight, shift_free=shift_free,
                        settings=settings.bundle, rolling=rolling)
    blurry_row = np.array([kinds[i] == "blurry" for i in index])
    errors = np.linalg.norm(res.residuals, axis=1)

    def median(mask: np.ndarray) -> float:
        e = errors[mask & res.inlier]
        return float(np.median(e)) if len(e) else float("nan")

    return GenericCalibration(
        model=res.model, parametric=camera, poses=dict(zip(frames, res.poses, strict=True)),
        shifts={f: res.shifts[i] for i, f in enumerate(frames) if shift_free[i]},
        frames=frames, blurry_frames=[f for f, k in zip(frames, kinds, strict=True) if k == "blurry"],
        frame=np.array(frames)[index], feature_id=ids, points=pts, weight=weight, observed=obs,
        residuals=res.residuals,
        inlier=res.inlier, median_error=res.median_error, rms_error=res.rms_error,
        sharp_median_error=median(~blurry_row), blurry_median_error=median(blurry_row),
        skipped_frames=skipped, route=settings.route, bundle=res,
        rolling={} if res.theta is None else {f: res.theta[i] for i, f in enumerate(frames) if moving[i]})


def difference_field(model: CentralGeneric, camera: BrownConrady | ParametricCamera, step: float = 8.0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Generic minus parametric over the calibrated area: ``(xs, ys, diff (H', W', 2))`` px.

    Each lattice pixel's generic ray, turned by the best-fit rotation between the two cameras'
    rays (the orientation is a gauge), is projected by ``camera``; the difference is that
    projection minus the pixel. NaN outside the area.
    """
    x0, y0, x1, y1 = model.area_opencv
    xs = np.arange(np.ceil(x0), x1, step)
    ys = np.arange(np.ceil(y0), y1, step)
    xx, yy = np.meshgrid(xs, ys)
    px = np.column_stack([xx.ravel(), yy.ravel()])
    g = model.pixel_to_ray(px)
    p = camera.pixel_to_ray(px)
    ok = np.all(np.isfinite(g), axis=1)
    Q = best_fit_rotation(g[ok], p[ok])
    diff = np.full(px.shape, np.nan)
    diff[ok] = camera.project(g[ok] @ Q.T) - px[ok]
    return xs, ys, diff.reshape(len(ys), len(xs), 2)


def _save_figure(fig: Figure, path: Path) -> None:
    FigureCanvasAgg(fig)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)


def _image_figure(values: np.ndarray, extent: tuple[float, float, float, float], title: str,
                  label: str) -> Figure:
    fig = Figure(figsize=(9, 5.4))
    ax = fig.add_subplot(1, 1, 1)
    im = ax.imshow(values, extent=extent, origin="upper", cmap="inferno", interpolation="nearest")
    ax.set_title(title)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    fig.colorbar(im, ax=ax, label=label)
    fig.tight_layout()
    return fig


def save_generic_calibration(out_dir: str | os.PathLike[str], result: GenericCalibration,
                             pinhole: BrownConrady | ParametricCamera | None = None,
                             undistort: str | OutputProjection = "auto") -> list[Path]:
    """Write the generic calibration's files into ``out_dir`` (e.g. ``OUT/calibration``).

    * ``intrinsics0.yaml``: the reference tool's CentralGenericModel file;
    * ``generic_poses.csv``: ``frame, tx, ty, tz, qx, qy, qz, qw`` (target -> camera, m), the
      reference tool's pose line layout, plus ``shift_x, shift_y`` (px);
    * ``undistortion_map.npz``: ``map_x, map_y`` (float32, for ``cv2.remap``) to the output image
      ``undistort`` (an :class:`blurcalib.camera.remap.OutputProjection`, or its kind for
      :func:`blurcalib.calib.undistortion.undistortion_output` with ``pinhole``), its ``K``
      (``fx, fy, cx, cy``), ``width``, ``height``, ``projection`` (its kind) and the generic
      camera's field ``field_deg``;
    * ``generic_coverage.png``: observations per grid cell; ``generic_minus_parametric.png``:
      the magnitude of :func:`difference_field`.

    Returns the written paths.
    """
    out = ensure_writable_dir(out_dir)
    model = result.model
    paths = [write_generic_yaml(out / INTRINSICS_FILE, model)]
    rows = []
    for name, pose in result.poses.items():
        qx, qy, qz, qw = _quaternion(pose.R)
        s = result.shifts.get(name, np.zeros(2))
        rows.append([name, *(f"{v:.12g}" for v in (*pose.t, qx, qy, qz, qw, *s))])
    paths.append(atomic_write_csv(out / POSES_FILE, ["frame", "tx", "ty", "tz", "qx", "qy", "qz", "qw",
                                                     "shift_x", "shift_y"], rows))
    output = (undistort if isinstance(undistort, OutputProjection)
              else undistortion_output(model, pinhole or result.parametric, undistort))
    paths.append(write_undistortion_map(out / UNDISTORTION_FILE, model, output))
    x0, y0, x1, y1 = model.area_opencv
    cov = result.bundle.coverage.astype(np.float64)
    fig = _image_figure(np.where(cov > 0, cov, np.nan), (x0, x1, y1, y0),
                        f"observations per grid cell ({int((cov == 0).sum())} empty cells)", "observations")
    _save_figure(fig, out / COVERAGE_FILE)
    paths.append(out / COVERAGE_FILE)
    xs, ys, diff = difference_field(model, result.parametric)
    mag = np.linalg.norm(diff, axis=2)
    step = xs[1] - xs[0] if len(xs) > 1 else 1.0
    fig = _image_figure(mag, (xs[0] - step / 2, xs[-1] + step / 2, ys[-1] + step / 2, ys[0] - step / 2),
                        f"generic minus parametric (median {np.nanmedian(mag):.3f} px, "
                        f"max {np.nanmax(mag):.3f} px)", "px")
    _save_figure(fig, out / DIFFERENCE_FILE)
    paths.append(out / DIFFERENCE_FILE)
    return paths


def _quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """``(qx, qy, qz, qw)`` of a rotation matrix (qw >= 0)."""
    rvec, _ = cv2.Rodrigues(np.ascontiguousarray(R))
    v = rvec.reshape(3)
    theta = float(np.linalg.norm(v))
    axis = v / theta if theta > 0 else np.zeros(3)
    s = np.sin(theta / 2)
    return float(axis[0] * s), float(axis[1] * s), float(axis[2] * s), float(np.cos(theta / 2))


def generic_report(result: GenericCalibration) -> dict[str, Any]:
    """The ``generic`` section of ``report.json``: model, errors (px), frames, coverage warnings."""
    b = result.bundle
    return {
        "model": "CentralGenericModel", "grid_width": result.model.grid_width,
        "grid_height": result.model.grid_height,
        "calibrated_area": [result.model.min_x, result.model.min_y, result.model.max_x, result.model.max_y],
        "route": result.route, "median_error_px": result.median_error, "rms_error_px": result.rms_error,
        "sharp_median_error_px": result.sharp_median_error,
        "blurry_median_error_px": result.blurry_median_error,
        "frames": len(result.poses), "blurry_frames": len(result.blurry_frames),
        "observations": len(result.inlier), "inliers": int(result.inlier.sum()),
        "iterations": b.iterations, "seconds": b.seconds, "warnings": b.warnings,
        "skipped_frames": result.skipped_frames,
    }
