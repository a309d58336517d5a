"""Undistorted output images of any central camera: a pinhole map for moderate fields, and a
latitude-longitude or stereographic map for wide ones (a pinhole image of a 180 degree field is
infinite).

An :class:`OutputProjection` says which direction (camera frame) each output pixel ``(x, y)``
(OpenCV convention) looks along, with ``a = (x - cx) / fx``, ``b = (y - cy) / fy``:

* ``pinhole``: ``(a, b, 1)``, normalised;
* ``latlong``: longitude ``a`` about the camera's y axis and latitude ``b`` (rad):
  ``(sin a cos b, sin b, cos a cos b)`` for ``|a| <= pi``, ``|b| <= pi / 2``;
* ``stereographic``: ``theta = 2 atan(r / 2)`` off the axis with ``r = |(a, b)|``:
  ``(sin(theta) (a, b) / r, cos theta)``;
* ``epipolar``: latitude ``b`` about the camera's x axis and ``a`` (rad) within that plane:
  ``(sin a, cos a sin b, cos a cos b)`` for ``|a| <= pi / 2``, ``|b| <= pi``. Each row is one
  plane through the x axis: the epipolar planes of a rectified pair whose baseline is that axis
  (:mod:`blurcalib.camera.stereo`), whatever the field of view.

All four look along the optical axis at the principal point with ``fx, fy`` px per radian there.
:func:`output_maps` gives ``cv2.remap`` maps from a camera's image to an output image;
:class:`RotatedCamera` is a camera seen from a turned frame (a rectified pair's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, cast

import cv2
import numpy as np
from numpy.typing import ArrayLike

__all__ = ["MAP_TOL_PX", "OUTPUT_KINDS", "PINHOLE_FIELD_DEG", "OutputProjection", "RayProjector",
           "RotatedCamera", "auto_output_kind", "central_pixel", "field_of_view_deg", "output_for",
           "output_maps"]

OUTPUT_KINDS = ("pinhole", "latlong", "stereographic", "epipolar")

MAP_TOL_PX = 1e-4
"""Convergence of :func:`output_maps`'s per-pixel projections (px): float32 maps of a 1280 px image
resolve about 1e-4 px."""

PINHOLE_FIELD_DEG = 120.0
"""Widest field (deg, full angle across the image) :func:`output_for` gives a pinhole output."""


class RayProjector(Protocol):
    """A camera that projects directions: the generic and the parametric models."""

    @property
    def width(self) -> int:
        """Image width (px)."""
        ...

    @property
    def height(self) -> int:
        """Image height (px)."""
        ...

    def project_valid(self, points: ArrayLike, init: ArrayLike | None = None, tol_px: float = 1e-8
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Pixels ``(N, 2)`` of camera-frame points ``(N, 3)`` and ``(N,) bool`` where valid."""
        ...

    def pixel_to_ray(self, px: ArrayLike) -> np.ndarray:
        """Unit directions ``(N, 3)`` of pixels ``(N, 2)``; NaN where none."""
        ...


@dataclass(frozen=True)
class OutputProjection:
    """An output image: its projection (module docstring), intrinsics (px, px per rad) and size."""

    kind: str
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.kind not in OUTPUT_KINDS:
            raise ValueError(f"unknown output projection {self.kind!r}; known: {', '.join(OUTPUT_KINDS)}")
        if not (self.fx > 0 and self.fy > 0 and self.width > 0 and self.height > 0):
            raise ValueError(f"output focal lengths and size must be positive, got fx={self.fx}, "
                             f"fy={self.fy}, {self.width} x {self.height}")

    def to_dict(self) -> dict[str, float | int | str]:
        """``projection`` (the kind), ``fx, fy`` (px, px per rad but for a pinhole), ``cx, cy`` (px,
        OpenCV pixels), ``width, height`` (px)."""
        return {"projection": self.kind, "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "width": self.width, "height": self.height}

    def rays(self, x: ArrayLike, y: ArrayLike) -> np.ndarray:
        """Unit directions ``(N, 3)`` of output pixels ``x, y (N,)``; NaN where the projection
        has none (beyond the poles of ``latlong``)."""
        a = (np.asarray(x, dtype=np.float64) - self.cx) / self.fx
        b = (np.asarray(y, dtype=np.float64) - self.cy) / self.fy
        if self.kind == "pinhole":
            rays = np.stack([a, b, np.ones_like(a)], axis=-1)
            return cast(np.ndarray, rays / np.linalg.norm(rays, axis=-1, keepdims=True))
        if self.kind == "latlong":
            rays = np.stack([np.sin(a) * np.cos(b), np.sin(b), np.cos(a) * np.cos(b)], axis=-1)
            rays[(np.abs(a) > math.pi) | (np.abs(b) > math.pi / 2)] = np.nan
            return rays
        if self.kind == "epipolar":
            rays = np.stack([np.sin(a), np.cos(a) * np.sin(b), np.cos(a) * np.cos(b)], axis=-1)
            rays[(np.abs(a) > math.pi / 2) | (np.abs(b) > math.pi)] = np.nan
            return rays
        r = np.hypot(a, b)
        theta = 2.0 * np.arctan(r / 2.0)
        scale = np.where(r > 0, np.sin(theta) / np.where(r > 0, r, 1.0), 1.0)
        return np.stack([a * scale, b * scale, np.cos(theta)], axis=-1)

    def project(self, directions: ArrayLike) -> np.ndarray:
        """Output pixels ``(N, 2)`` of directions ``(N, 3)`` (any length; the inverse of
        :meth:`rays`); NaN where the projection has none (a pinhole's ``Z <= 0``, a stereographic
        output's backward axis)."""
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        x, y, z = d[:, 0], d[:, 1], d[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.kind == "pinhole":
                a, b = np.where(z > 0, x / z, np.nan), np.where(z > 0, y / z, np.nan)
            elif self.kind == "latlong":
                a, b = np.arctan2(x, z), np.arcsin(np.clip(y, -1.0, 1.0))
            elif self.kind == "epipolar":
                a, b = np.arcsin(np.clip(x, -1.0, 1.0)), np.arctan2(y, z)
            else:
                rho = np.hypot(x, y)
                r = np.where(z > -1.0, 2.0 * np.tan(np.arctan2(rho, z) / 2.0), np.nan)
                scale = np.where(rho > 0, r / np.where(rho > 0, rho, 1.0), 2.0)
                a, b = x * scale, y * scale
        return np.column_stack([a * self.fx + self.cx, b * self.fy + self.cy])


@dataclass(frozen=True, eq=False)
class RotatedCamera:
    """A camera seen from a turned frame: ``X_new = R X_cam`` (``R (3, 3)``, e.g. a rectifying
    rotation), itself a :class:`RayProjector` (rays and projections in the new frame)."""

    camera: RayProjector
    R: np.ndarray

    @property
    def width(self) -> int:
        """Image width (px)."""
        return self.camera.width

    @property
    def height(self) -> int:
        """Image height (px)."""
        return self.camera.height

    def project_valid(self, points: ArrayLike, init: ArrayLike | None = None, tol_px: float = 1e-8
                      ) -> tuple[np.ndarray, np.ndarray]:
        """The camera's pixels of new-frame points ``(N, 3)`` (``X_cam = R^T X_new``)."""
        return self.camera.project_valid(np.asarray(points, dtype=np.float64).reshape(-1, 3) @ self.R, init,
                                         tol_px=tol_px)

    def pixel_to_ray(self, px: ArrayLike) -> np.ndarray:
        """Unit new-frame directions ``(N, 3)`` of pixels ``(N, 2)``; NaN where none."""
        return self.camera.pixel_to_ray(px) @ np.asarray(self.R, dtype=np.float64).T


def _projected_radius(kind: str, theta: float) -> float:
    """An output projection's radius (per unit focal length) of a ray ``theta`` off the axis."""
    if kind == "pinhole":
        return math.tan(theta) if theta < math.pi / 2 else math.inf
    return 2.0 * math.tan(theta / 2.0) if kind == "stereographic" else theta


def field_of_view_deg(camera: RayProjector, lattice: int = 64) -> float:
    """The camera's field (deg, full angle): twice the widest angle between its optical axis (the
    ray of the image centre) and the ray of any pixel it has, over a ``lattice x lattice`` grid of
    the image (a generic camera's rays outside its calibrated area do not count)."""
    w, h = camera.width, camera.height
    xs, ys = np.meshgrid(np.linspace(0.0, w - 1.0, lattice), np.linspace(0.0, h - 1.0, lattice))
    theta = _off_axis(camera, np.column_stack([xs.reshape(-1), ys.reshape(-1)]))
    return 2.0 * math.degrees(float(theta.max(initial=0.0)))


def _probe_step(camera: RayProjector) -> float:
    """The distance (px) of the pixels whose rays give the focal length near the centre."""
    return max(1.0, 0.01 * min(camera.width, camera.height))


def central_pixel(camera: RayProjector) -> np.ndarray:
    """``(2,)``: the image centre, or, where the camera has no ray there (a generic camera whose
    calibrated area leaves it out), the pixel nearest it on a 33 x 33 lattice of the image whose
    ray and the rays :func:`_probe_step` px to each side exist.

    Raises:
        ValueError: no such pixel (a camera without rays).
    """
    w, h = camera.width, camera.height
    d = _probe_step(camera)
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    xs, ys = np.meshgrid(np.linspace(d, w - 1 - d, 33), np.linspace(d, h - 1 - d, 33))
    candidates = np.vstack([centre, np.column_stack([xs.ravel(), ys.ravel()])])
    candidates = candidates[np.argsort(np.linalg.norm(candidates - centre, axis=1), kind="stable")]
    offsets = np.array([[0.0, 0.0], [-d, 0.0], [d, 0.0], [0.0, -d], [0.0, d]])
    rays = camera.pixel_to_ray((candidates[:, None, :] + offsets).reshape(-1, 2))
    ok = np.all(np.isfinite(rays.reshape(len(candidates), 5, 3)), axis=(1, 2))
    if not ok.any():
        raise ValueError(f"the {w} x {h} camera has no rays: it has no calibrated area")
    return cast(np.ndarray, candidates[int(np.argmax(ok))])


def _off_axis(camera: RayProjector, px: np.ndarray) -> np.ndarray:
    """Angles (rad) between the optical axis (the ray of :func:`central_pixel`, the image centre's
    where it has one) and the rays of pixels ``(N, 2)`` that have one."""
    axis = camera.pixel_to_ray(central_pixel(camera)[None])[0]
    rays = camera.pixel_to_ray(px)
    return np.asarray(np.arccos(np.clip(rays[np.all(np.isfinite(rays), axis=1)] @ axis, -1.0, 1.0)))


def auto_output_kind(camera: RayProjector) -> str:
    """``pinhole`` for a field (:func:`field_of_view_deg`) up to :data:`PINHOLE_FIELD_DEG`,
    ``latlong`` beyond (any field up to 360 degrees, at the same px per radian along the middle
    row and column)."""
    return "pinhole" if field_of_view_deg(camera) <= PINHOLE_FIELD_DEG else "latlong"


def output_for(camera: RayProjector, kind: str | None = None) -> OutputProjection:
    """The output image of a camera: its size, principal point at the image centre, and its
    px per radian near the centre (at :func:`central_pixel`) as focal length, lowered where
    needed so that the rays of the middle row and column (as far as the camera has rays) stay in
    the output (a pinhole output keeps the centre's scale).

    ``kind`` None: :func:`auto_output_kind`.
    """
    w, h = camera.width, camera.height
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    delta = _probe_step(camera)
    probe = camera.pixel_to_ray(central_pixel(camera)
                                + np.array([[-delta, 0.0], [delta, 0.0], [0.0, -delta], [0.0, delta]]))
    angle = [math.acos(float(np.clip(probe[i] @ probe[i + 1], -1.0, 1.0))) for i in (0, 2)]
    fx, fy = 2.0 * delta / angle[0], 2.0 * delta / angle[1]
    kind = auto_output_kind(camera) if kind is None else kind
    if kind != "pinhole":
        t = np.linspace(0.0, 1.0, 129)
        row = np.column_stack([t * (w - 1), np.full_like(t, centre[1])])
        column = np.column_stack([np.full_like(t, centre[0]), t * (h - 1)])
        theta = [_off_axis(camera, px).max(initial=0.0) for px in (row, column)]
        if min(theta) > 0:
            reach = min((w - 1) / 2.0 / _projected_radius(kind, float(theta[0])),
                        (h - 1) / 2.0 / _projected_radius(kind, float(theta[1])))
            scale = min(1.0, reach / max(fx, fy))
            fx, fy = fx * scale, fy * scale
    return OutputProjection(kind, fx, fy, float(centre[0]), float(centre[1]), w, h)


def output_maps(camera: RayProjector, output: OutputProjection, coarse_px: int = 16,
                tol_px: float = MAP_TOL_PX) -> tuple[np.ndarray, np.ndarray]:
    """Maps for ``cv2.remap`` from the camera's image to the output image.

    ``map_x, map_y (output.height, output.width)`` float32 hold each output pixel's position in
    the camera's image (OpenCV pixels), -1 where its ray has no valid pixel (outside the
    calibrated area or the image, or beyond the output projection), so ``remap`` fills the
    border value there. Each pixel's projection is solved to ``tol_px``, warm-started from a
    bilinear interpolation of a solve every ``coarse_px`` pixels.
    """
    width, height = output.width, output.height

    def rays(xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        xx, yy = np.meshgrid(xs, ys)
        return output.rays(xx.reshape(-1), yy.reshape(-1))

    def project(directions: np.ndarray, init: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The camera's pixels (-1 for rays the output projection lacks) and where valid."""
        px = np.full((len(directions), 2), -1.0)
        ok = np.all(np.isfinite(directions), axis=1)
        if ok.any():
            px[ok], inside = camera.project_valid(directions[ok], None if init is None else init[ok],
                                                  tol_px=tol_px)
            ok[ok] = inside
        return px, ok

    cxs = np.append(np.arange(0, width - 1, coarse_px, dtype=np.float64), width - 1)
    cys = np.append(np.arange(0, height - 1, coarse_px, dtype=np.float64), height - 1)
    coarse, _ = project(rays(cxs, cys), None)
    coarse = coarse.reshape(len(cys), len(cxs), 2)
    fx_idx = np.interp(np.arange(width), cxs, np.arange(len(cxs))).astype(np.float32)
    fy_idx = np.interp(np.arange(height), cys, np.arange(len(cys))).astype(np.float32)
    grid = np.meshgrid(fx_idx, fy_idx)
    init = np.stack([cv2.remap(coarse[..., k].astype(np.float32), *grid, cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REPLICATE) for k in range(2)], -1).reshape(-1, 2)
    all_rays = rays(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    out = np.empty((len(all_rays), 2))
    chunk = 1 << 17
    for i in range(0, len(all_rays), chunk):
        u, inside = project(all_rays[i:i + chunk], init[i:i + chunk].astype(np.float64))
        u[~inside] = -1.0
        out[i:i + chunk] = u
    maps = out.reshape(height, width, 2).astype(np.float32)
    return np.ascontiguousarray(maps[..., 0]), np.ascontiguousarray(maps[..., 1])
