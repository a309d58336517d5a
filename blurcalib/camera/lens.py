"""The parametric camera family: one interface for Brown-Conrady, OpenCV's rational model,
Kannala-Brandt (``cv::fisheye``) and the reference tool's thin-prism fisheye.

A model works with *viewing directions*, not normalised image coordinates, so that a ray may
leave the front half-space (a fisheye sees up to 100 degrees off the axis and more).

Projection of a camera-frame point ``P = (X, Y, Z)`` (any scale; ``rho = sqrt(X^2 + Y^2)``,
``theta = atan2(rho, Z)`` its angle off the optical axis)::

    m = (X / Z, Y / Z)                  perspective base point (Brown-Conrady, rational)
    m = theta (X, Y) / rho              equidistant base point (Kannala-Brandt, fisheye)
    u = (fx d_x(m) + cx, fy d_y(m) + cy)

with the distortion ``d`` of :mod:`blurcalib.camera.distortion`. Unprojection inverts ``d``
(a 1-D solve of the radial part, then Newton on the whole map) and turns the base point back
into a unit direction. The *valid field* is where the radial map ``r -> |d(r, 0)|`` increases
(up to :attr:`ParametricCamera.max_angle` off the axis), the 2-D map is locally invertible
(``det dd/dm > 0``), and, for a perspective model, ``Z > 0``.

Pixels follow OpenCV (top-left pixel centre at ``(0, 0)``); the parameter vector starts with
``fx, fy, cx, cy`` (px) followed by the model's distortion coefficients (unitless).
:func:`project_poses_camera` is :func:`blurcalib.camera.parametric.project_poses` for any model.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar, cast

import numpy as np
from numpy.typing import ArrayLike

from blurcalib.camera.distortion import (
    COEFFICIENTS,
    distort,
    distort_with_jacobian,
    radial_map,
    radial_slope_root,
)
from blurcalib.camera.parametric import Projection, as_int, rodrigues_jacobian
from blurcalib.geometry.pose import as_points

__all__ = ["ParametricCamera", "base_point", "direction_of_base", "project_poses_camera"]

_SERIES_U = 1e-3
"""Below this ``rho / Z`` the equidistant base point uses its Taylor series (error ~1e-25)."""
_NEWTON_ITERATIONS = 40
_SOLVED = 1e-11
"""A base point whose distortion misses the pixel's by more than this (normalised units, about
1e-8 px) has no ray."""


def _as_size(value: Any, name: str) -> int:
    """A positive integer image size."""
    size = as_int(value, name)
    if size <= 0:
        raise ValueError(f"{name} must be positive, got {size}")
    return size


def base_point(points: np.ndarray, angular: bool, jacobian: bool = False
               ) -> tuple[np.ndarray, np.ndarray | None]:
    """The base point ``m (N, 2)`` of camera-frame points ``(N, 3)`` and ``dm/dP (N, 2, 3)``.

    Perspective: ``m = (X, Y) / Z``. Equidistant: ``m = s (X, Y)`` with ``s = theta / rho``;
    ``ds/dX = X (Z rho / |P|^2 - theta) / rho^3`` (same in ``Y``), ``ds/dZ = -1 / |P|^2``; near
    the axis (``rho < 1e-3 Z``) by the series ``s = (1 - u^2/3 + u^4/5 - u^6/7) / Z`` and
    ``(Z rho / |P|^2 - theta) / rho^3 = (-2/3 + 4 u^2/5 - 6 u^4/7) / Z^3``, ``u = rho / Z``.
    """
    X, Y, Z = points[:, 0], points[:, 1], points[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        if not angular:
            m = np.stack([X / Z, Y / Z], axis=1)
            if not jacobian:
                return m, None
            J = np.zeros((len(points), 2, 3))
            J[:, 0, 0] = J[:, 1, 1] = 1.0 / Z
            J[:, 0, 2] = -X / (Z * Z)
            J[:, 1, 2] = -Y / (Z * Z)
            return m, J
        rho2 = X * X + Y * Y
        rho = np.sqrt(rho2)
        n2 = rho2 + Z * Z
        theta = np.arctan2(rho, Z)
        u = rho / Z
        near = (Z > 0) & (rho < _SERIES_U * Z)
        u2 = np.where(near, u * u, 0.0)
        s = np.where(near, (1.0 - u2 / 3.0 + u2 * u2 / 5.0 - u2 ** 3 / 7.0) / Z, theta / rho)
        m = np.stack([s * X, s * Y], axis=1)
        if not jacobian:
            return m, None
        f = np.where(near, (-2.0 / 3.0 + 0.8 * u2 - 6.0 / 7.0 * u2 * u2) / Z ** 3,
                     (Z * rho / n2 - theta) / (rho * rho2))
        ds = np.stack([X * f, Y * f, -1.0 / n2], axis=1)  # (N, 3)
        J = np.stack([X, Y], axis=1)[:, :, None] * ds[:, None, :]
        J[:, 0, 0] += s
        J[:, 1, 1] += s
        return m, J


def direction_of_base(m: np.ndarray, angular: bool) -> np.ndarray:
    """Unit directions ``(N, 3)`` of base points ``m (N, 2)``: ``normalize(x, y, 1)`` or, for the
    equidistant base, ``(sin(theta) m / theta, cos(theta))`` with ``theta = |m|``."""
    if not angular:
        rays = np.concatenate([m, np.ones((len(m), 1))], axis=1)
        return cast(np.ndarray, rays / np.linalg.norm(rays, axis=1, keepdims=True))
    theta = np.linalg.norm(m, axis=1)
    sinc = np.sinc(theta / np.pi)  # sin(theta) / theta
    return np.column_stack([m * sinc[:, None], np.cos(theta)])


@dataclass(frozen=True, eq=False)
class ParametricCamera:
    """A parametric central camera: a base point of the viewing direction, a distortion, ``K``.

    Subclasses (one module each) fix :attr:`MODEL`, :attr:`PARAM_NAMES` (``fx, fy, cx, cy``
    and the distortion coefficients), :attr:`KERNEL_INDEX` (each distortion coefficient's place
    in :data:`blurcalib.camera.distortion.COEFFICIENTS`) and :attr:`ANGULAR` (the equidistant
    base point).

    Attributes:
        params: ``(P,)`` float64, in :attr:`PARAM_NAMES` order (read-only).
        width, height: image size (px).
    """

    params: np.ndarray
    width: int
    height: int

    MODEL: ClassVar[str] = ""
    PARAM_NAMES: ClassVar[tuple[str, ...]] = ()
    KERNEL_INDEX: ClassVar[tuple[int, ...]] = ()
    ANGULAR: ClassVar[bool] = False
    OPENCV_DISTORTION: ClassVar[tuple[str, ...] | None] = None
    """The names of OpenCV's distortion vector of this model, in OpenCV's order (None: OpenCV
    has no such model)."""

    def __post_init__(self) -> None:
        params = np.array(self.params, dtype=np.float64).reshape(-1)
        if params.shape != (len(self.PARAM_NAMES),):
            raise ValueError(f"{self.MODEL} needs {len(self.PARAM_NAMES)} parameters "
                             f"{list(self.PARAM_NAMES)}, got {params.size}")
        if not np.all(np.isfinite(params)):
            raise ValueError(f"{self.MODEL} parameters must be finite, got {params.tolist()}")
        if params[0] <= 0 or params[1] <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={params[0]}, fy={params[1]}")
        params.setflags(write=False)
        object.__setattr__(self, "params", params)
        object.__setattr__(self, "width", _as_size(self.width, "width"))
        object.__setattr__(self, "height", _as_size(self.height, "height"))

    # -- parameters ----------------------------------------------------------------------
    @classmethod
    def from_values(cls, width: int, height: int, **values: float) -> ParametricCamera:
        """The camera with the named parameters (missing distortion coefficients are 0)."""
        unknown = sorted(set(values) - set(cls.PARAM_NAMES))
        if unknown:
            raise ValueError(f"{cls.MODEL} has no parameters {unknown}; it has {list(cls.PARAM_NAMES)}")
        for name in cls.PARAM_NAMES[:4]:
            if name not in values:
                raise ValueError(f"{cls.MODEL} needs parameter {name!r}")
        return cls(np.array([float(values.get(n, 0.0)) for n in cls.PARAM_NAMES]), width, height)

    @property
    def angular(self) -> bool:
        """Whether the base point is equidistant (``theta`` off the axis) or perspective."""
        return self.ANGULAR

    def named(self) -> dict[str, float]:
        """``{name: value}`` of every parameter."""
        return {name: float(v) for name, v in zip(self.PARAM_NAMES, self.params, strict=True)}

    @property
    def fx(self) -> float:
        return float(self.params[0])

    @property
    def fy(self) -> float:
        return float(self.params[1])

    @property
    def cx(self) -> float:
        return float(self.params[2])

    @property
    def cy(self) -> float:
        return float(self.params[3])

    @property
    def K(self) -> np.ndarray:
        """``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (3, 3) px."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def with_params(self, params: ArrayLike) -> ParametricCamera:
        """The same model with another parameter vector ``(P,)``."""
        return dataclasses.replace(self, params=np.asarray(params, dtype=np.float64))

    def replace(self, **values: float) -> ParametricCamera:
        """Copy with the named parameters replaced."""
        unknown = sorted(set(values) - set(self.PARAM_NAMES))
        if unknown:
            raise ValueError(f"{self.MODEL} has no parameters {unknown}")
        params = self.params.copy()
        for name, value in values.items():
            params[self.PARAM_NAMES.index(name)] = float(value)
        return self.with_params(params)

    def scaled(self, s: float) -> ParametricCamera:
        """The camera of the image resized by ``s``: ``f' = s f``, ``c' = s (c + 0.5) - 0.5``."""
        s = float(s)
        if not math.isfinite(s) or s <= 0.0:
            raise ValueError(f"scale factor must be positive and finite, got {s}")
        p = self.params.copy()
        p[:2] *= s
        p[2:4] = s * (p[2:4] + 0.5) - 0.5
        return dataclasses.replace(self, params=p, width=max(1, round(s * self.width)),
                                   height=max(1, round(s * self.height)))

    @cached_property
    def coefficients(self) -> np.ndarray:
        """``(11,)`` the distortion kernel's coefficient vector of this camera."""
        c = np.zeros(len(COEFFICIENTS))
        c[list(self.KERNEL_INDEX)] = self.params[4:]
        return c

    # -- the valid field -------------------------------------------------------------------
    @cached_property
    def max_base_radius(self) -> float:
        """The largest base radius of the valid field: where the radial map stops increasing,
        and at most ``pi`` (equidistant) or ``inf`` (perspective)."""
        limit = math.pi if self.angular else math.pi / 2
        theta = np.linspace(0.0, limit, 4097)[1:]
        radii = theta if self.angular else np.tan(np.minimum(theta, limit - 1e-9))
        return min(radial_slope_root(self.coefficients, radii), math.pi if self.angular else math.inf)

    @property
    def max_angle(self) -> float:
        """The valid field's half angle off the optical axis (rad): up to ``pi`` for an
        equidistant base, ``pi / 2`` for a perspective one."""
        r = self.max_base_radius
        return r if self.angular else math.atan(r)

    def valid_directions(self, points: ArrayLike) -> np.ndarray:
        """``(N,) bool``: camera-frame points ``(N, 3)`` in the valid field (module docstring)."""
        pts = as_points(points, 3, "points").reshape(-1, 3)
        m, _ = base_point(pts, self.angular)
        r = np.linalg.norm(m, axis=1)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(r) & (r < self.max_base_radius)
            if not self.angular:
                ok &= pts[:, 2] > 0
            J = distort_with_jacobian(np.nan_to_num(m), self.coefficients).d_m
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        return cast(np.ndarray, ok & (det > 0))

    def in_image(self, px: ArrayLike) -> np.ndarray:
        """``(N,) bool``: pixels ``(N, 2)`` on the sensor, ``[-0.5, W - 0.5) x [-0.5, H - 0.5)``."""
        p = as_points(px, 2, "px").reshape(-1, 2)
        return ((p[:, 0] >= -0.5) & (p[:, 0] < self.width - 0.5)
                & (p[:, 1] >= -0.5) & (p[:, 1] < self.height - 0.5))

    # -- projection --------------------------------------------------------------------------
    def project(self, points: ArrayLike) -> np.ndarray:
        """Camera-frame points ``(N, 3)`` (any scale) -> pixels ``(N, 2)`` px.

        Points outside the valid field are projected by the same formula (as
        ``cv2.projectPoints`` does); :meth:`project_valid` says which are valid.
        """
        pts = as_points(points, 3, "points")
        m, _ = base_point(pts.reshape(-1, 3), self.angular)
        d = distort(m, self.coefficients)
        px = d * self.params[:2] + self.params[2:4]
        return cast(np.ndarray, px.reshape(*pts.shape[:-1], 2))

    def project_valid(self, points: ArrayLike, init: ArrayLike | None = None, tol_px: float = 0.0
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Pixels ``(N, 2)`` of points ``(N, 3)`` and ``(N,) bool``: in the valid field and on the
        sensor. ``init`` and ``tol_px`` (a start and the tolerance of the generic model's iterative
        projection, :class:`blurcalib.camera.remap.RayProjector`) are not needed: the projection is
        closed-form."""
        del init, tol_px
        pts = as_points(points, 3, "points").reshape(-1, 3)
        px = self.project(pts)
        return px, self.valid_directions(pts) & self.in_image(px)

    def project_with_jacobian(self, points: ArrayLike) -> Projection:
        """Pixels of points ``(N, 3)`` with ``d_intrinsics (N, 2, P)`` (:attr:`PARAM_NAMES`
        order) and ``d_point (N, 2, 3)`` (``d_pose`` is None).

        ``du/dP = diag(fx, fy) dd/dm dm/dP``; ``du/d(fx, fy, cx, cy) = (d_x, 0), (0, d_y), (1, 0),
        (0, 1)``; ``du/dk = diag(fx, fy) dd/dc`` for the model's kernel coefficients.
        """
        pts = as_points(points, 3, "points").reshape(-1, 3)
        m, dm = base_point(pts, self.angular, jacobian=True)
        dist = distort_with_jacobian(m, self.coefficients)
        f = self.params[:2]
        px = dist.d * f + self.params[2:4]
        n = len(pts)
        d_intr = np.zeros((n, 2, len(self.params)))
        d_intr[:, 0, 0] = dist.d[:, 0]
        d_intr[:, 1, 1] = dist.d[:, 1]
        d_intr[:, 0, 2] = 1.0
        d_intr[:, 1, 3] = 1.0
        d_intr[:, :, 4:] = dist.d_c[:, :, list(self.KERNEL_INDEX)] * f[None, :, None]
        d_point = (dist.d_m * f[None, :, None]) @ dm
        return Projection(px, d_intr, None, d_point)

    # -- unprojection ------------------------------------------------------------------------
    def _radial_solve(self, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Base radii ``r (N,)`` with ``g(r) = target`` on ``[0, max_base_radius)`` (Newton kept
        inside a shrinking bracket) and whether one exists."""
        c = self.coefficients
        hi_r = self.max_base_radius
        if not math.isfinite(hi_r):
            hi_r = max(1.0, float(target.max(initial=0.0)))
            while radial_map(np.array([hi_r]), c)[0][0] < target.max(initial=0.0) and hi_r < 1e8:
                hi_r *= 2.0
        reach = radial_map(np.array([hi_r]), c)[0][0]
        exists = target <= reach
        lo = np.zeros_like(target)
        hi = np.full_like(target, hi_r)
        r = np.clip(target, 0.0, hi_r)
        for _ in range(100):
            g, slope = radial_map(r, c)
            err = g - target
            lo = np.where(err < 0, r, lo)
            hi = np.where(err > 0, r, hi)
            with np.errstate(divide="ignore", invalid="ignore"):
                step = r - err / slope
            bad = ~np.isfinite(step) | (step <= lo) | (step >= hi)
            new = np.where(bad, 0.5 * (lo + hi), step)
            if np.all(np.abs(new - r) <= 1e-15 * (1.0 + r)):
                r = new
                break
            r = new
        return r, exists

    def undistort(self, md: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Base points ``m (N, 2)`` with ``d(m) = md`` for distorted base points ``md (N, 2)``,
        and ``(N,) bool`` whether one exists in the valid field.

        The radial part is solved first (1-D), then Newton's method on the whole map (each step
        halved until the residual decreases) to about 1e-16.
        """
        md = as_points(md, 2, "md").reshape(-1, 2)
        target = np.linalg.norm(md, axis=1)
        r, exists = self._radial_solve(target)
        with np.errstate(divide="ignore", invalid="ignore"):
            m = np.where((target > 0)[:, None], md * (r / target)[:, None], 0.0)
        c = self.coefficients
        err = distort(m, c) - md
        cost = (err * err).sum(axis=1)
        going = np.flatnonzero(cost > 0)
        for _ in range(_NEWTON_ITERATIONS):
            if len(going) == 0:
                break
            J = distort_with_jacobian(m[going], c).d_m
            e = err[going]
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.stack([J[:, 1, 1] * e[:, 0] - J[:, 0, 1] * e[:, 1],
                                 J[:, 0, 0] * e[:, 1] - J[:, 1, 0] * e[:, 0]], axis=1) / det[:, None]
            improved = np.zeros(len(going), dtype=bool)
            for scale in (1.0, 0.5, 0.25):
                cand = m[going] - scale * step
                cerr = distort(np.nan_to_num(cand), c) - md[going]
                ccost = (cerr * cerr).sum(axis=1)
                take = ~improved & np.isfinite(ccost) & (ccost < cost[going])
                idx = going[take]
                m[idx], err[idx], cost[idx] = cand[take], cerr[take], ccost[take]
                improved |= take
            going = going[improved & (cost[going] > 0)]
        with np.errstate(invalid="ignore"):
            J = distort_with_jacobian(m, c).d_m
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            ok = (exists & (np.sqrt(cost) < _SOLVED * (1.0 + target))
                  & (np.linalg.norm(m, axis=1) < self.max_base_radius) & (det > 0))
        return m, ok

    def unproject(self, px: ArrayLike) -> np.ndarray:
        """Pixels ``(N, 2)`` px -> unit viewing directions ``(N, 3)``; NaN where the pixel has no
        ray in the valid field."""
        p = as_points(px, 2, "px")
        flat = p.reshape(-1, 2)
        md = (flat - self.params[2:4]) / self.params[:2]
        m, ok = self.undistort(md)
        rays = direction_of_base(m, self.angular)
        rays[~ok] = np.nan
        return rays.reshape(*p.shape[:-1], 3)

    pixel_to_ray = unproject

    def valid_pixels(self, px: ArrayLike) -> np.ndarray:
        """``(N,) bool``: pixels ``(N, 2)`` that have a ray in the valid field."""
        return cast(np.ndarray, np.all(np.isfinite(self.unproject(px).reshape(-1, 3)), axis=1))

    # -- files -------------------------------------------------------------------------------
    def _extra(self) -> dict[str, Any]:
        """Model options beyond the parameter vector (none here)."""
        return {}

    def to_dict(self) -> dict[str, Any]:
        """``{"model", "width", "height", "parameters": {name: value}}`` (JSON-serialisable)."""
        return {"model": self.MODEL, "width": self.width, "height": self.height, **self._extra(),
                "parameters": self.named()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ParametricCamera:
        """Inverse of :meth:`to_dict`; raises ValueError naming a missing or unknown key."""
        if not isinstance(data, Mapping):
            raise ValueError(f"camera description must be a mapping, got {type(data).__name__}")
        if data.get("model") != cls.MODEL:
            raise ValueError(f"camera model is {data.get('model')!r}, expected {cls.MODEL!r}")
        for key in ("width", "height", "parameters"):
            if key not in data:
                raise ValueError(f"camera description is missing key {key!r}")
        values = data["parameters"]
        if not isinstance(values, Mapping):
            raise ValueError("camera description: 'parameters' must be a mapping of names to values")
        missing = [n for n in cls.PARAM_NAMES if n not in values]
        if missing:
            raise ValueError(f"camera description is missing parameters {missing}")
        unknown = sorted(set(values) - set(cls.PARAM_NAMES))
        if unknown:
            raise ValueError(f"camera description has unknown parameters {unknown}")
        extra = {k: data[k] for k in data if k not in ("model", "width", "height", "parameters")}
        return cls._build(np.array([float(values[n]) for n in cls.PARAM_NAMES]), data["width"],
                          data["height"], extra)

    @classmethod
    def _build(cls, params: np.ndarray, width: int, height: int, extra: Mapping[str, Any]
               ) -> ParametricCamera:
        """The camera from :meth:`from_dict`'s parts (``extra``: the model's options)."""
        if extra:
            raise ValueError(f"camera description has unknown keys {sorted(extra)}")
        return cls(params, width, height)


def project_poses_camera(camera: ParametricCamera, rvecs: ArrayLike, tvecs: ArrayLike, points: ArrayLike,
                         frame_idx: ArrayLike | None = None, *, jacobian: bool = False) -> Projection:
    """``pi(R_f P + t_f)`` of ``N`` observations through any parametric camera, batched over
    frames, with its analytic Jacobian: :func:`blurcalib.camera.parametric.project_poses` for the
    whole family (``d_intrinsics (N, 2, P)`` in the camera's :attr:`~ParametricCamera.PARAM_NAMES`
    order).

    Args:
        camera: the model and its intrinsics.
        rvecs, tvecs: ``(F, 3)`` poses, target -> camera (rad, m).
        points: ``(N, 3)`` target point of each observation (m).
        frame_idx: ``(N,)`` frame of each observation (None: all frame 0).
        jacobian: whether to return the derivatives.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    fi = np.zeros(len(points), dtype=np.int64) if frame_idx is None else np.asarray(frame_idx)
    R, dR = rodrigues_jacobian(rvecs)
    Rn = R[fi]
    cam = np.einsum("nab,nb->na", Rn, points) + np.asarray(tvecs, dtype=np.float64).reshape(-1, 3)[fi]
    if not jacobian:
        return Projection(camera.project(cam))
    proj = camera.project_with_jacobian(cam)
    A = proj.d_point
    dcam_dr = np.einsum("nkab,nb->nak", dR[fi], points)
    return Projection(proj.pixels, proj.d_intrinsics, np.concatenate([A @ dcam_dr, A], axis=2), A @ Rn)
