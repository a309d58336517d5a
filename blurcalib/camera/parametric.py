"""The parametric (Brown-Conrady) camera: its projection with the Jacobian and its files.

Poses are :class:`blurcalib.geometry.pose.Pose`; homographies are in :mod:`blurcalib.geometry.homography`.

Conventions
-----------
* Pixels follow OpenCV: the centre of the top-left pixel is ``(0, 0)`` px, x points right
  and y points down.
* A pose maps target (world) coordinates to camera coordinates,
  ``X_cam = R X_world + t`` (metres). The calibration target is the plane ``Z_world = 0``;
  metric target points are ``(X, Y, 0)`` m.
* The lens model ``Brown_Conrady`` is OpenCV's five-coefficient model with coefficients in
  OpenCV order ``(k1, k2, p1, p2, k3)``. For normalised coordinates ``x = (X/Z, Y/Z)`` and
  ``r^2 = x^2 + y^2``::

      d(x) = (1 + k1 r^2 + k2 r^4 + k3 r^6) x
             + (2 p1 x y + p2 (r^2 + 2 x^2),  p1 (r^2 + 2 y^2) + 2 p2 x y)

  and a camera point ``M`` in pose ``P`` projects to ``pi_d(M, P) = K (d([M P]~), 1)`` with
  ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``.
* The target-plane homography (paper equation ``eq:T``) is ``H = K [r1 r2 t]``; it maps
  target-plane metres ``(X, Y, 1)`` to *undistorted* pixel coordinates.

Functions work in float64 on arrays of shape ``(..., N, 2)`` / ``(..., N, 3)``;
:func:`project_poses` is the one projection with its analytic Jacobian, batched over frames.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import cv2
import numpy as np
from numpy.typing import ArrayLike

from blurcalib.camera.storage import CameraFileError, StorageReader, read_text, write_storage
from blurcalib.geometry.pose import Pose, as_points
from blurcalib.io.atomic import atomic_write_text

if TYPE_CHECKING:
    from blurcalib.camera.lens import ParametricCamera

__all__ = [
    "BrownConrady",
    "CameraFileError",
    "Projection",
    "load_camera_json",
    "load_camera_yaml",
    "project_points",
    "project_poses",
    "rodrigues_jacobian",
    "save_camera_json",
    "save_camera_yaml",
]


MODEL_NAME = "Brown_Conrady"
_INTRINSIC_FIELDS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
_SIZE_FIELDS = ("width", "height")


# ---------------------------------------------------------------------------
# Distortion kernels (pure arithmetic).
# ---------------------------------------------------------------------------


def _distort_xy(x: np.ndarray, y: np.ndarray, k1: float, k2: float, p1: float, p2: float, k3: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Brown-Conrady distortion ``d(x)`` of normalised coordinates, component-wise."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    two_xy = 2.0 * x * y
    xd = radial * x + p1 * two_xy + p2 * (r2 + 2.0 * x * x)
    yd = radial * y + p1 * (r2 + 2.0 * y * y) + p2 * two_xy
    return xd, yd


def _distort_jacobian(
    x: np.ndarray, y: np.ndarray, k1: Any, k2: Any, p1: Any, p2: Any, k3: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Entries ``(J_xx, J_xy, J_yy)`` of the symmetric Jacobian ``dd/dx`` of ``d(x)``."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    jxx = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    jxy = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    jyy = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return jxx, jxy, jyy


def _undistort_step(
    x: np.ndarray,
    y: np.ndarray,
    xd: np.ndarray,
    yd: np.ndarray,
    coeffs: tuple[Any, ...],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One safeguarded step towards the solution of ``d(x) = xd``.

    Three candidates are evaluated per point: a full Newton step, a half Newton step and
    the classical fixed-point step ``x <- (xd - tangential(x)) / radial(x)``. The candidate
    with the smallest squared residual is kept if it improves on the current point.
    Returns the new ``(x, y)`` and its squared residual ``|d(x) - xd|^2``.
    """
    dx, dy = _distort_xy(x, y, *coeffs)
    ex = dx - xd
    ey = dy - yd
    best_x, best_y, best_err = x, y, ex * ex + ey * ey
    jxx, jxy, jyy = _distort_jacobian(x, y, *coeffs)
    det = jxx * jyy - jxy * jxy
    step_x = (jyy * ex - jxy * ey) / det
    step_y = (jxx * ey - jxy * ex) / det
    r2 = x * x + y * y
    radial = 1.0 + r2 * (coeffs[0] + r2 * (coeffs[1] + r2 * coeffs[4]))
    candidates = (
        (x - step_x, y - step_y),
        (x - 0.5 * step_x, y - 0.5 * step_y),
        (x - ex / radial, y - ey / radial),
    )
    for cand_x, cand_y in candidates:
        cdx, cdy = _distort_xy(cand_x, cand_y, *coeffs)
        cex = cdx - xd
        cey = cdy - yd
        cand_err = cex * cex + cey * cey
        better = cand_err < best_err
        best_x = np.where(better, cand_x, best_x)
        best_y = np.where(better, cand_y, best_y)
        best_err = np.where(better, cand_err, best_err)
    return best_x, best_y, best_err


def _dist_from_array(dist: ArrayLike) -> tuple[float, float, float, float, float]:
    """OpenCV distortion vector (4, 5, 8, 12 or 14 entries) -> ``(k1, k2, p1, p2, k3)``.

    Entries beyond the fifth belong to other OpenCV models and must be zero.
    """
    arr = np.asarray(dist, dtype=np.float64).reshape(-1)
    if arr.size not in (4, 5, 8, 12, 14):
        raise ValueError(f"distortion must have 4, 5, 8, 12 or 14 coefficients, got {arr.size}")
    if arr.size > 5 and np.any(arr[5:] != 0.0):
        raise ValueError(
            "distortion coefficients beyond (k1, k2, p1, p2, k3) are non-zero; "
            f"only the {MODEL_NAME} model is supported"
        )
    full = np.zeros(5)
    full[: min(arr.size, 5)] = arr[:5]
    k1, k2, p1, p2, k3 = (float(v) for v in full)
    return k1, k2, p1, p2, k3


def as_int(value: Any, name: str) -> int:
    """Integer-valued ``value`` as int; rejects bools and non-integral numbers."""
    if isinstance(value, bool | np.bool_):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    try:
        as_float = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be an integer, got {value!r}") from exc
    if not math.isfinite(as_float) or as_float != int(as_float):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    return int(as_float)


# ---------------------------------------------------------------------------
# Camera model
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class BrownConrady:
    """Pinhole camera with OpenCV's five-coefficient Brown-Conrady distortion.

    Attributes:
        fx, fy: focal lengths (px).
        cx, cy: principal point (px), OpenCV pixel-centre convention.
        k1, k2, k3: radial distortion coefficients (unitless).
        p1, p2: tangential distortion coefficients (unitless).
        width, height: image size (px).

    The projection is ``pi_d(M, P) = K (d([M P]~), 1)`` (``Brown_Conrady`` in the paper).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float
    k2: float
    p1: float
    p2: float
    k3: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in _INTRINSIC_FIELDS:
            value = getattr(self, name)
            try:
                as_float = float(value)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{name} must be a real number, got {value!r}") from exc
            if not math.isfinite(as_float):
                raise ValueError(f"{name} must be finite, got {value!r}")
            object.__setattr__(self, name, as_float)
        if self.fx <= 0.0 or self.fy <= 0.0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        for name in _SIZE_FIELDS:
            size = as_int(getattr(self, name), name)
            if size <= 0:
                raise ValueError(f"{name} must be positive, got {size}")
            object.__setattr__(self, name, size)

    @classmethod
    def from_matrix(cls, K: ArrayLike, dist: ArrayLike | None, width: int, height: int) -> BrownConrady:
        """Build from an OpenCV camera matrix ``K (3, 3)`` and distortion vector.

        ``dist`` holds 4, 5, 8, 12 or 14 OpenCV coefficients (entries after ``k3`` must be
        zero) or is ``None`` for no distortion. Skewed camera matrices are rejected.
        """
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"camera matrix must have shape (3, 3), got {K.shape}")
        if K[0, 1] != 0.0 or K[1, 0] != 0.0 or np.any(K[2] != (0.0, 0.0, 1.0)):
            raise ValueError(
                f"camera matrix must have the form [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}"
            )
        k1, k2, p1, p2, k3 = _dist_from_array(np.zeros(5) if dist is None else dist)
        return cls(
            fx=K[0, 0],
            fy=K[1, 1],
            cx=K[0, 2],
            cy=K[1, 2],
            k1=k1,
            k2=k2,
            p1=p1,
            p2=p2,
            k3=k3,
            width=width,
            height=height,
        )

    @property
    def K(self) -> np.ndarray:
        """Camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, shape (3, 3), px."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """Distortion coefficients ``(k1, k2, p1, p2, k3)`` in OpenCV order, shape (5,)."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def params(self) -> np.ndarray:
        """``(9,)`` ``fx, fy, cx, cy, k1, k2, p1, p2, k3``: the intrinsics of
        :func:`project_poses` and of the calibration's parameter vector."""
        return np.array([self.fx, self.fy, self.cx, self.cy, self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def _coeffs(self) -> tuple[float, float, float, float, float]:
        return self.k1, self.k2, self.p1, self.p2, self.k3

    def with_params(self, **changes: Any) -> BrownConrady:
        """Copy with the named fields replaced (validated like the constructor)."""
        return dataclasses.replace(self, **changes)

    def scaled(self, s: float) -> BrownConrady:
        """Camera for the image resized by factor ``s``.

        With the pixel-centre convention a pixel coordinate maps as ``x' = s (x + 0.5) - 0.5``,
        so ``f' = s f`` and ``c' = s (c + 0.5) - 0.5``; the image size becomes
        ``round(s * size)`` px and the (normalised) distortion is unchanged.
        """
        s = float(s)
        if not math.isfinite(s) or s <= 0.0:
            raise ValueError(f"scale factor must be positive and finite, got {s}")
        return dataclasses.replace(
            self,
            fx=s * self.fx,
            fy=s * self.fy,
            cx=s * (self.cx + 0.5) - 0.5,
            cy=s * (self.cy + 0.5) - 0.5,
            width=max(1, round(s * self.width)),
            height=max(1, round(s * self.height)),
        )

    def distort(self, xn: ArrayLike) -> np.ndarray:
        """Distort normalised coordinates: ``xn (N, 2)`` -> ``d(xn) (N, 2)`` (unitless)."""
        xn = as_points(xn, 2, "xn")
        xd, yd = _distort_xy(xn[..., 0], xn[..., 1], *self._coeffs)
        return np.stack([xd, yd], axis=-1)

    def undistort(self, xd: ArrayLike, *, max_iter: int = 50) -> np.ndarray:
        """Invert :meth:`distort`: distorted ``xd (N, 2)`` -> normalised ``x (N, 2)``.

        Solves ``d(x) = xd`` with safeguarded Newton iterations (falling back to half steps
        and to OpenCV's fixed-point update), starting from ``x = xd``. For realistic
        distortion the result is accurate to ~1e-15 in normalised units after a handful of
        iterations. Points where ``d`` is not invertible get the best iterate found. A point
        whose step finds no better candidate would find none again, so the later iterations
        step only the points that moved.
        """
        xd = as_points(xd, 2, "xd")
        tx, ty = xd[..., 0].reshape(-1), xd[..., 1].reshape(-1)
        x, y = tx.copy(), ty.copy()
        err = np.full(tx.shape, np.inf)
        going = np.arange(tx.size)  # a point whose step did not improve it stays where it is
        with np.errstate(all="ignore"):
            for _ in range(max_iter):
                nx, ny, new_err = _undistort_step(x[going], y[going], tx[going], ty[going], self._coeffs)
                better = new_err < err[going]
                if not better.any():
                    break
                going = going[better]
                x[going], y[going], err[going] = nx[better], ny[better], new_err[better]
        return np.stack([x, y], axis=-1).reshape(xd.shape)

    def project(self, points_cam: ArrayLike) -> np.ndarray:
        """Project camera-frame points ``(N, 3)`` m to distorted pixels ``(N, 2)`` px.

        ``u = K (d(X/Z, Y/Z), 1)``. Points with ``Z <= 0`` are projected by the same
        formula (as ``cv2.projectPoints`` does); filter them beforehand if needed.
        """
        pts = as_points(points_cam, 3, "points_cam")
        xd, yd = _distort_xy(pts[..., 0] / pts[..., 2], pts[..., 1] / pts[..., 2], *self._coeffs)
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)

    def unproject(self, px: ArrayLike, *, max_iter: int = 50) -> np.ndarray:
        """Distorted pixels ``(N, 2)`` px -> undistorted normalised coordinates ``(N, 2)``.

        Equivalent to ``cv2.undistortPoints`` without ``R``/``P`` but solved to full
        precision (see :meth:`undistort`).
        """
        px = as_points(px, 2, "px")
        xd = np.stack([(px[..., 0] - self.cx) / self.fx, (px[..., 1] - self.cy) / self.fy], -1)
        return self.undistort(xd, max_iter=max_iter)

    def pixel_to_ray(self, px: ArrayLike) -> np.ndarray:
        """Distorted pixels ``(N, 2)`` px -> unit viewing rays ``(N, 3)`` in the camera frame."""
        xn = self.unproject(px)
        rays = np.concatenate([xn, np.ones((*xn.shape[:-1], 1))], axis=-1)
        return cast(np.ndarray, rays / np.linalg.norm(rays, axis=-1, keepdims=True))

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable dict: ``model`` plus every field (floats px/unitless, ints px)."""
        out: dict[str, Any] = {"model": MODEL_NAME}
        out.update({name: getattr(self, name) for name in _INTRINSIC_FIELDS + _SIZE_FIELDS})
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> BrownConrady:
        """Inverse of :meth:`to_dict`.

        Raises:
            ValueError: missing key (named in the message), unknown key, wrong ``model``
                or an invalid value.
        """
        if not isinstance(data, Mapping):
            raise ValueError(f"camera description must be a mapping, got {type(data).__name__}")
        fields = _INTRINSIC_FIELDS + _SIZE_FIELDS
        for name in fields:
            if name not in data:
                raise ValueError(f"camera description is missing key {name!r}")
        unknown = sorted(set(data) - set(fields) - {"model"})
        if unknown:
            raise ValueError(f"camera description has unknown keys {unknown}")
        model = data.get("model", MODEL_NAME)
        if model != MODEL_NAME:
            raise ValueError(f"unsupported camera model {model!r}, expected {MODEL_NAME!r}")
        return cls(**{name: data[name] for name in fields})


def project_points(camera: BrownConrady, pose: Pose, points_world: ArrayLike) -> np.ndarray:
    """Project world points ``(N, 3)`` m to distorted pixels ``(N, 2)`` px.

    ``pi_d(M, P) = K (d([M P]~), 1)`` with ``[M P]~`` the dehomogenised camera point.
    """
    return camera.project(pose.transform(points_world))


def rodrigues_jacobian(rvecs: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Rodrigues: ``rvecs (F, 3)`` rad -> ``R (F, 3, 3)`` and ``dR (F, 3, 3, 3)``,
    ``dR[f, k] = dR_f / dr_k``."""
    rvecs = np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)
    R = np.empty((len(rvecs), 3, 3))
    dR = np.empty((len(rvecs), 3, 3, 3))
    for f, rvec in enumerate(rvecs):
        rot, jac = cv2.Rodrigues(np.ascontiguousarray(rvec))
        R[f] = rot
        dR[f] = jac.reshape(3, 3, 3)
    return R, dR


@dataclass(frozen=True, eq=False)
class Projection:
    """Pixels of :func:`project_poses` and, when asked, their Jacobians.

    Attributes:
        pixels: ``(N, 2)`` px, OpenCV convention.
        d_intrinsics: ``(N, 2, 9)`` w.r.t. ``fx, fy, cx, cy, k1, k2, p1, p2, k3``.
        d_pose: ``(N, 2, 6)`` w.r.t. the observation's ``(rvec, tvec)`` (rad, m).
        d_point: ``(N, 2, 3)`` w.r.t. the target point (m).
    """

    pixels: np.ndarray
    d_intrinsics: np.ndarray | None = None
    d_pose: np.ndarray | None = None
    d_point: np.ndarray | None = None


def project_poses(intrinsics: ArrayLike, rvecs: ArrayLike, tvecs: ArrayLike, points: ArrayLike,
                  frame_idx: ArrayLike | None = None, *, jacobian: bool = False) -> Projection:
    """``pi_d(M_f, P) = K (d([R_f P + t_f]~), 1)`` of ``N`` observations, batched over frames,
    with its analytic Jacobian (the one projection of the calibration and alignment solvers).

    Args:
        intrinsics: ``(9,)`` ``fx, fy, cx, cy, k1, k2, p1, p2, k3`` (px and unitless), the
            order of :data:`BrownConrady.params`.
        rvecs, tvecs: ``(F, 3)`` poses, target -> camera (rad, m).
        points: ``(N, 3)`` target point of each observation (m).
        frame_idx: ``(N,)`` frame of each observation (None: all frame 0).
        jacobian: whether to return the derivatives.
    """
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = np.asarray(intrinsics, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    fi = np.zeros(len(points), dtype=np.int64) if frame_idx is None else np.asarray(frame_idx)
    R, dR = rodrigues_jacobian(rvecs)
    Rn = R[fi]
    cam = np.einsum("nab,nb->na", Rn, points) + np.asarray(tvecs, dtype=np.float64).reshape(-1, 3)[fi]
    inv_z = 1.0 / cam[:, 2]
    x, y = cam[:, 0] * inv_z, cam[:, 1] * inv_z
    xd, yd = _distort_xy(x, y, k1, k2, p1, p2, k3)
    pixels = np.stack([fx * xd + cx, fy * yd + cy], axis=1)
    if not jacobian:
        return Projection(pixels)
    n = len(points)
    r2 = x * x + y * y
    r4 = r2 * r2
    xy2 = 2.0 * x * y
    zero, one = np.zeros(n), np.ones(n)
    d_intr = np.stack([
        np.stack([xd, zero, one, zero, fx * x * r2, fx * x * r4, fx * xy2, fx * (r2 + 2 * x * x),
                  fx * x * r4 * r2], axis=1),
        np.stack([zero, yd, zero, one, fy * y * r2, fy * y * r4, fy * (r2 + 2 * y * y), fy * xy2,
                  fy * y * r4 * r2], axis=1)], axis=1)
    jxx, jxy, jyy = _distort_jacobian(x, y, k1, k2, p1, p2, k3)
    dnorm = np.zeros((n, 2, 3))
    dnorm[:, 0, 0] = inv_z
    dnorm[:, 1, 1] = inv_z
    dnorm[:, 0, 2] = -x * inv_z
    dnorm[:, 1, 2] = -y * inv_z
    Jd = np.stack([np.stack([fx * jxx, fx * jxy], axis=1), np.stack([fy * jxy, fy * jyy], axis=1)], axis=1)
    A = Jd @ dnorm  # d(u, v) / d(X_cam)
    dcam_dr = np.einsum("nkab,nb->nak", dR[fi], points)
    return Projection(pixels, d_intr, np.concatenate([A @ dcam_dr, A], axis=2), A @ Rn)


# Camera files
# ---------------------------------------------------------------------------


def save_camera_yaml(path: str | os.PathLike[str], camera: BrownConrady) -> None:
    """Write ``camera`` as OpenCV FileStorage YAML, atomically.

    Keys: ``camera_matrix`` (3x3), ``distortion_coefficients`` (1x5, OpenCV order),
    ``image_width``, ``image_height`` (px). Doubles are written with 17 significant
    digits, so :func:`load_camera_yaml` restores the camera exactly.
    """
    write_storage(path, {"camera_matrix": camera.K, "distortion_coefficients": camera.dist.reshape(1, 5),
                         "image_width": camera.width, "image_height": camera.height})


def load_camera_yaml(path: str | os.PathLike[str]) -> BrownConrady:
    """Read a camera written by :func:`save_camera_yaml` (or by OpenCV calibration tools).

    ``distortion_coefficients`` may hold 4, 5, 8, 12 or 14 values (entries after ``k3``
    must be zero).

    Raises:
        CameraFileError: missing, unreadable or malformed file; the message names the file.
    """
    with StorageReader(path) as file:
        file.require("camera_matrix", "distortion_coefficients", "image_width", "image_height")
        K, dist = file.matrix("camera_matrix"), file.matrix("distortion_coefficients")
        width, height = (as_int(file.number(key), key) for key in ("image_width", "image_height"))
        return BrownConrady.from_matrix(K, dist, width, height)


def save_camera_json(path: str | os.PathLike[str], camera: BrownConrady | ParametricCamera) -> None:
    """Write ``camera.to_dict()`` as JSON, atomically (floats round-trip exactly)."""
    atomic_write_text(path, json.dumps(camera.to_dict(), indent=2) + "\n")


def load_camera_json(path: str | os.PathLike[str]) -> BrownConrady:
    """Read a camera written by :func:`save_camera_json`.

    Raises:
        CameraFileError: missing, unreadable or malformed file, or a missing/invalid key;
            the message names the file and the problem.
    """
    name = os.fspath(path)
    text = read_text(path)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CameraFileError(f"camera file {name!r} is not valid JSON: {exc}") from exc
    try:
        return BrownConrady.from_dict(data)
    except ValueError as exc:
        raise CameraFileError(f"camera file {name!r} is invalid: {exc}") from exc
