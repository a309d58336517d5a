"""Where each sensor sub-sample looks on the renderer's canvas: the lens map.

The renderer (:mod:`blurcalib.sim.render`) warps the target's texture onto a pinhole *canvas*
once per time sample (a homography) and maps the time integral through the lens once.

* The forward-looking lens (:class:`blurcalib.camera.parametric.BrownConrady`): one canvas for
  every frame, the undistorted perspective image covering the sensor
  (:func:`perspective_lens_map`).
* Any lens of the parametric family, up to a 200 degree field (:class:`WideLens`): per frame a
  canvas *rotated to face the target*: its optical axis is the target plane's normal on the
  camera's side, so the plane (seen from one side, within one half-space of directions) maps
  to it by a similarity at ``f_c / D`` canvas px per metre (``D`` the plane's distance). Each
  sensor sub-sample's ray ``v`` lands at ``K_c (R_c v)``; rays that miss the canvas see the
  background, rays beyond the lens's field stop are dark. ``f_c`` is chosen so that canvas
  pixels are no coarser than the sensor's sub-samples anywhere on the visible target.

Sub-sample ``(i, j)`` of a ``supersample`` s sensor is pixel ``((j + 0.5) / s - 0.5,
(i + 0.5) / s - 0.5)`` (OpenCV convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import cast

import cv2
import numpy as np
from scipy.interpolate import RectBivariateSpline

from blurcalib.geometry.pose import Pose
from blurcalib.sim.truth import TrueCamera

__all__ = ["LensMap", "WideLens", "perspective_lens_map"]

OFF_CANVAS = -1.0e6
"""Map value of a sub-sample whose ray cannot meet the canvas (``cv2.remap`` reads the border)."""
MAX_CANVAS_SAMPLES = 16_000_000
"""Largest canvas (samples); a finer one would be needed only for a target seen edge-on at close
range, and is coarsened to this size."""
_COARSE_STEP = 4
"""Sub-samples between the lattice points where the lens is solved exactly (splines between)."""
_BAND_ROWS = 256


@dataclass(frozen=True, eq=False)
class LensMap:
    """A canvas and where each sensor sub-sample looks on it.

    Attributes:
        K: ``(3, 3)`` the canvas's pinhole intrinsics (canvas px).
        R: ``(3, 3)`` rotation camera -> canvas frame, or None (the camera's own axes).
        size: ``(cw, ch)`` canvas size (px).
        map_x, map_y: ``(H s, W s)`` float32 canvas position of each sensor sub-sample
            (:data:`OFF_CANVAS` where its ray cannot meet the canvas).
        dark: ``(H s, W s)`` bool, sub-samples beyond the lens's field stop, or None.
    """

    K: np.ndarray
    R: np.ndarray | None
    size: tuple[int, int]
    map_x: np.ndarray
    map_y: np.ndarray
    dark: np.ndarray | None = None
    rows: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] = field(init=False)

    def __post_init__(self) -> None:
        on = self.map_x > OFF_CANVAS / 2
        big, small = np.float32(np.inf), np.float32(-np.inf)
        bounds = (np.where(on, self.map_x, big).min(axis=1), np.where(on, self.map_x, small).max(axis=1),
                  np.where(on, self.map_y, big).min(axis=1), np.where(on, self.map_y, small).max(axis=1))
        object.__setattr__(self, "rows", bounds)

    def homography(self, pose: Pose, shift: np.ndarray | None = None) -> np.ndarray:
        """``(3, 3)`` target plane ``(X, Y, 1)`` m -> canvas px: ``S K (R) [r1 r2 t]`` (``eq:T``),
        ``S`` a canvas shift ``(3, 3)`` (None: identity)."""
        M = self.K if shift is None else shift @ self.K
        if self.R is not None:
            M = M @ self.R
        return cast(np.ndarray, M @ np.column_stack([pose.R[:, 0], pose.R[:, 1], pose.t]))

    def box(self, s0: int, s1: int) -> tuple[int, int, int, int] | None:
        """The canvas box ``(x0, y0, x1, y1)`` sub-sample rows ``s0 .. s1 - 1`` look into (with a
        1 px margin), or None when none of them meets the canvas."""
        min_x, max_x, min_y, max_y = (b[s0:s1] for b in self.rows)
        lo_x, lo_y = float(min_x.min()), float(min_y.min())
        if not math.isfinite(lo_x):
            return None
        cw, ch = self.size
        x0 = max(0, math.floor(lo_x) - 1)
        y0 = max(0, math.floor(lo_y) - 1)
        x1 = min(cw, math.ceil(float(max_x.max())) + 2)
        y1 = min(ch, math.ceil(float(max_y.max())) + 2)
        return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def _fine_grid(camera: TrueCamera, ss: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fine sub-sample indices along x and y, and the coarse lattice of them (every
    :data:`_COARSE_STEP`, the last included)."""
    fine_x = np.arange(camera.width * ss)
    fine_y = np.arange(camera.height * ss)
    coarse_x = np.append(fine_x[::_COARSE_STEP], fine_x[-1])
    coarse_y = np.append(fine_y[::_COARSE_STEP], fine_y[-1])
    return fine_x, fine_y, coarse_x, coarse_y


def perspective_lens_map(camera: TrueCamera, ss: int) -> LensMap:
    """The forward-looking lens's canvas: the undistorted perspective image of the whole sensor
    at ``f ss`` px per normalised unit, with a 4 px margin.

    The lens map is smooth: it is solved exactly on a coarse lattice of sub-samples and
    interpolated with bicubic splines (error far below 1e-3 px).
    """
    fine_x, fine_y, coarse_x, coarse_y = _fine_grid(camera, ss)
    gx, gy = np.meshgrid((coarse_x + 0.5) / ss - 0.5, (coarse_y + 0.5) / ss - 0.5)
    xn = camera.unproject(np.stack([gx.ravel(), gy.ravel()], axis=1))
    lo = xn.min(axis=0)
    hi = xn.max(axis=0)
    f = np.array([camera.model.fx, camera.model.fy]) * ss
    margin = 4.0
    K = np.array([[f[0], 0.0, -lo[0] * f[0] + margin],
                  [0.0, f[1], -lo[1] * f[1] + margin],
                  [0.0, 0.0, 1.0]])
    size = (math.ceil((hi[0] - lo[0]) * f[0] + 2 * margin), math.ceil((hi[1] - lo[1]) * f[1] + 2 * margin))
    maps = []
    for axis in range(2):
        coarse = (xn[:, axis] * f[axis] + K[axis, 2]).reshape(len(coarse_y), -1)
        spline = RectBivariateSpline(coarse_y, coarse_x, coarse, kx=3, ky=3)
        maps.append(spline(fine_y, fine_x).astype(np.float32))
    return LensMap(K, None, size, maps[0], maps[1])


def _canvas_rotation(axis: np.ndarray) -> np.ndarray:
    """A rotation whose third row is the unit ``axis`` (camera -> canvas frame), its first row
    as close to the camera's x axis as possible."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ axis) * axis
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(axis, x), axis])


class WideLens:
    """Per-frame canvases for any lens of the parametric family (module docstring).

    The sensor's viewing directions are solved on a coarse lattice of sub-samples once and
    interpolated with bicubic splines per frame; sub-samples beyond the field stop are dark.
    """

    def __init__(self, camera: TrueCamera, ss: int) -> None:
        self.camera = camera
        self.ss = ss
        fine_x, fine_y, coarse_x, coarse_y = _fine_grid(camera, ss)
        self._fine = (fine_x, fine_y)
        gx, gy = np.meshgrid((coarse_x + 0.5) / ss - 0.5, (coarse_y + 0.5) / ss - 0.5)
        rays = camera.pixel_to_ray(np.stack([gx.ravel(), gy.ravel()], axis=1))
        if not np.all(np.isfinite(rays)):
            raise ValueError(f"the lens has no ray for some pixels of its image (its valid field ends "
                             f"{math.degrees(camera.field_stop):.1f} degrees off the axis or before); "
                             "the simulator needs one everywhere")
        self._rays = rays.reshape(len(coarse_y), len(coarse_x), 3)
        self._splines = [RectBivariateSpline(coarse_y, coarse_x, self._rays[..., k], kx=3, ky=3)
                         for k in range(3)]
        cos_stop = math.cos(camera.field_stop)
        self._seen = rays[:, 2] >= cos_stop
        self.dark = np.concatenate([self._splines[2](fine_y[i:i + _BAND_ROWS], fine_x) < cos_stop
                                    for i in range(0, len(fine_y), _BAND_ROWS)])

    def _visible_density(self, pose: Pose, plane_points: np.ndarray) -> float:
        """The largest sensor px per metre (largest singular value of ``d pi / d(X, Y)``) over
        target-plane points ``(N, 2)`` m seen on the sensor at ``pose``."""
        cam = pose.transform(np.column_stack([plane_points, np.zeros(len(plane_points))]))
        px = self.camera.project(cam)
        seen = self.camera.in_view(cam) & (px[:, 0] >= -0.5) & (px[:, 0] < self.camera.width - 0.5) \
            & (px[:, 1] >= -0.5) & (px[:, 1] < self.camera.height - 0.5)
        if not seen.any():
            seen = self.camera.in_view(cam)
        J = self.camera.point_jacobian(cam[seen]) @ pose.R[:, :2]
        return float(np.linalg.svd(J, compute_uv=False)[:, 0].max(initial=1e-9))

    def frame_map(self, pose: Pose, poses: list[Pose], extent: np.ndarray) -> LensMap:
        """The canvas facing the target at ``pose`` (tau = 0), covering the target's texture
        ``extent (4, 2)`` (plane corners, m) at every time sample ``poses`` where the sensor sees
        it, and where each sub-sample looks on it."""
        normal = pose.R[:, 2]
        offset = float(normal @ pose.t)
        axis = normal if offset > 0 else -normal
        Rc = _canvas_rotation(axis)
        distance = abs(offset)
        grid = np.linspace(0.0, 1.0, 17)
        u, v = np.meshgrid(grid, grid)
        lo, hi = extent.min(axis=0), extent.max(axis=0)
        samples = np.column_stack([lo[0] + u.ravel() * (hi[0] - lo[0]), lo[1] + v.ravel() * (hi[1] - lo[1])])
        focal = self.ss * distance * self._visible_density(pose, samples)
        corners = np.concatenate([Rc @ (p.R[:, :2] @ extent.T + p.t[:, None]) for p in poses], axis=1)
        if np.any(corners[2] <= 0):
            raise ValueError("a time sample sees the target from its other side; the motion is too large")
        box_lo, box_hi = (corners[:2] / corners[2]).min(axis=1), (corners[:2] / corners[2]).max(axis=1)
        rays = self._rays.reshape(-1, 3) @ Rc.T
        seen = self._seen & (rays[:, 2] > 1e-6)
        if seen.any():
            ray_xy = rays[seen, :2] / rays[seen, 2:]
            box_lo = np.maximum(box_lo, ray_xy.min(axis=0) - 0.01)
            box_hi = np.minimum(box_hi, ray_xy.max(axis=0) + 0.01)
        box_hi = np.maximum(box_hi, box_lo)
        area = float(np.prod(box_hi - box_lo)) * focal * focal
        if area > MAX_CANVAS_SAMPLES:
            focal *= math.sqrt(MAX_CANVAS_SAMPLES / area)
        margin = 4.0
        K = np.array([[focal, 0.0, margin - focal * box_lo[0]], [0.0, focal, margin - focal * box_lo[1]],
                      [0.0, 0.0, 1.0]])
        size = (math.ceil((box_hi[0] - box_lo[0]) * focal + 2 * margin) + 1,
                math.ceil((box_hi[1] - box_lo[1]) * focal + 2 * margin) + 1)
        map_x, map_y = self._maps(Rc, K)
        return LensMap(K, Rc, size, map_x, map_y, self.dark)

    def _maps(self, Rc: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Canvas positions ``K (R_c v)`` of every sub-sample's ray ``v`` (band by band)."""
        fine_x, fine_y = self._fine
        map_x = np.empty((len(fine_y), len(fine_x)), dtype=np.float32)
        map_y = np.empty_like(map_x)
        for i in range(0, len(fine_y), _BAND_ROWS):
            comps = [s(fine_y[i:i + _BAND_ROWS], fine_x) for s in self._splines]
            q = [Rc[k, 0] * comps[0] + Rc[k, 1] * comps[1] + Rc[k, 2] * comps[2] for k in range(3)]
            ok = q[2] > 1e-6
            with np.errstate(divide="ignore", invalid="ignore"):
                for out, k in ((map_x, 0), (map_y, 1)):
                    pos = K[k, k] * q[k] / q[2] + K[k, 2]
                    pos = np.clip(pos, OFF_CANVAS / 4, -OFF_CANVAS)
                    out[i:i + _BAND_ROWS] = np.where(ok, pos, OFF_CANVAS)
        return map_x, map_y

    def level_lambda(self, lens: LensMap, pose: Pose, texel_m: float, levels: int, step: int = 16
                     ) -> np.ndarray:
        """``(ch, cw)`` float32 mip level ``log2 rho`` per canvas px, clipped to ``[0, levels - 1]``:
        ``rho`` finest-level texels per sensor sub-sample at the target point under it,
        ``1 / (texel_m s sqrt|det d pi / d(X, Y)|)``; where the sensor does not see the point,
        texels per canvas px."""
        cw, ch = lens.size
        ys, xs = np.mgrid[0:ch + step:step, 0:cw + step:step].astype(np.float64)
        G = np.linalg.inv(lens.homography(pose))
        h = G @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
        plane = (h[:2] / h[2]).T
        cam = pose.transform(np.column_stack([plane, np.zeros(len(plane))]))
        distance = abs(float(pose.R[:, 2] @ pose.t))
        rho = np.full(len(plane), distance / (texel_m * lens.K[0, 0]))
        seen = self.camera.in_view(cam)
        if seen.any():
            J = self.camera.point_jacobian(cam[seen]) @ pose.R[:, :2]
            det = np.abs(J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0])
            rho[seen] = 1.0 / (texel_m * self.ss * np.sqrt(np.maximum(det, 1e-300)))
        lam = np.clip(np.log2(np.maximum(rho, 1e-12)), 0, levels - 1).reshape(xs.shape)
        return cast(np.ndarray, cv2.resize(lam.astype(np.float32), (xs.shape[1] * step, xs.shape[0] * step),
                                           interpolation=cv2.INTER_LINEAR)[:ch, :cw])
