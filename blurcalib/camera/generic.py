"""The central generic camera model: a B-spline grid of viewing directions (Schöps et al. 2020).

This is the reference tool's ``CentralGenericModel`` (``models/central_generic.h``), so that its
files interoperate (:mod:`blurcalib.camera.files` reads and writes them).

Model
-----
* A ``GH x GW`` grid of unit 3D direction vectors ``v_{r,c}`` (``grid (GH, GW, 3)``), with one
  exterior cell outside the calibrated area on each side.
* The calibrated area is ``[min_x, max_x + 1) x [min_y, max_y + 1)`` in the reference tool's
  *pixel-corner* convention (the top-left pixel's centre at ``(0.5, 0.5)``): the integer bounding
  box of the features. blurcalib's pixels use OpenCV's convention, so ``x_corner = x + 0.5``.
* Pixel to grid coordinate::

      g_x = 1 + (GW - 3) (x_corner - min_x) / (max_x + 1 - min_x)     (same in y)

  so the calibrated area maps to ``[1, GW - 2) x [1, GH - 2)``.
* Unprojection: the uniform cubic B-spline surface of the raw node vectors (node ``k`` at grid
  coordinate ``k``; at an integer coordinate nodes ``k-1, k, k+1`` weigh ``1/6, 4/6, 1/6``),
  then normalised: ``d(u) = s(g(u)) / |s(g(u))|`` with ``s(g) = sum_{r,c} B(g_y - r) B(g_x - c) v_{r,c}``.
* Projection (direction to pixel) has no closed form: a batched 2-D Levenberg-Marquardt solve of
  ``min_u |d(u) - p / |p||^2``, clamped to the calibrated area, warm-startable. Its derivatives
  follow by implicit differentiation of ``d(u) = p / |p|`` (see :func:`projection_jacobians`).
* Updates: two parameters per node in its tangent plane, ``v <- normalize(v + a t1 + b t2)`` with
  ``t1 = normalize(v x (1, 0, 0))`` (``v x (0, 1, 0)`` when ``|v_x| > 0.9``) and ``t2 = v x t1``.
  Parameter ``2 (r GW + c) + {0, 1}`` is ``(a, b)`` of node ``(r, c)``.

The math runs batched in torch (float64, any device); the dataclass offers NumPy wrappers.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import scipy.linalg
import torch
from numpy.typing import ArrayLike

from blurcalib.camera.remap import OutputProjection, output_maps
from blurcalib.camera.spline_projection import PROJECTION_DAMPING, SplineProjection
from blurcalib.optim.lm import LmRule, Stopping, run_batch

__all__ = [
    "DEFAULT_CELL_PX",
    "CentralGeneric",
    "GridSpline",
    "accumulate_blocks",
    "apply_update",
    "calibrated_area",
    "check_grid_size",
    "fit_to_rays",
    "grid_size_for",
    "param_columns",
    "projection_jacobians",
    "tangent_basis",
    "undistortion_map",
]

DEFAULT_CELL_PX = 25.0
"""The reference tool's default grid cell length (px)."""

PIXEL_CORNER_OFFSET = 0.5
"""Reference-tool (pixel-corner) coordinate minus OpenCV coordinate (px)."""

_EDGE_ITERATIONS = 6
"""A projection held at the area's edge for this many iterations is given up (outside the area)."""
_WARM_DAMPING = 1e-6
"""Initial Levenberg-Marquardt damping of a warm-started projection, relative to the normal
matrix's diagonal: from a previous iterate's pixel the first steps are Gauss-Newton's (the
lattice start far from the solution uses 0.005)."""

_AREA_EDGE = 0.999
"""Projections are clamped to ``[min, max + 0.999]`` (pixel-corner), as the reference does."""


MAX_GRID_NODES = 5000
"""Most nodes of a generic grid fitted by the bundle adjustment. Its reduced normal equations on
the ``2 GW GH`` grid parameters are dense (:mod:`blurcalib.calib.bundle`): three such float64 matrices,
``96 GW^2 GH^2`` bytes, about 2.4 GB at 5000 nodes (a 1920 x 1080 camera at 25 px cells has
3555). Larger grids are refused before anything is allocated, naming the cell length that fits."""


def grid_size_for(length_px: float, cell_px: float = DEFAULT_CELL_PX) -> int:
    """Nodes along one axis for a calibrated length: ``int(length / cell + 0.5) + 2``, at least 4."""
    if not (math.isfinite(cell_px) and cell_px > 0):
        raise ValueError(f"cell length must be a finite positive number of px, got {cell_px}")
    return max(4, int(length_px / cell_px + 0.5) + 2)


def check_grid_size(width_px: float, height_px: float, cell_px: float = DEFAULT_CELL_PX) -> tuple[int, int]:
    """The grid ``(GH, GW)`` for a calibrated area of ``width_px x height_px`` at cells of
    ``cell_px``, checked against :data:`MAX_GRID_NODES`.

    Raises:
        ValueError: a cell length that is not a finite positive number, or a grid of more than
            :data:`MAX_GRID_NODES` nodes (the message gives the memory it would need and the
            smallest cell length that fits).
    """
    gh, gw = grid_size_for(height_px, cell_px), grid_size_for(width_px, cell_px)
    if gh * gw <= MAX_GRID_NODES:
        return gh, gw
    fits = max(1.0, math.floor(cell_px))
    while grid_size_for(height_px, fits) * grid_size_for(width_px, fits) > MAX_GRID_NODES:
        fits += 1.0
    need_gb = 96.0 * (gh * gw) ** 2 / 1e9
    raise ValueError(f"cells of {cell_px:g} px make a {gw} x {gh} grid ({gh * gw} nodes) over "
                     f"{width_px:g} x {height_px:g} px, whose bundle adjustment would need about "
                     f"{need_gb:,.1f} GB; the limit is {MAX_GRID_NODES} nodes: use cells of {fits:g} px "
                     f"or more")


def calibrated_area(px: ArrayLike, width: int, height: int) -> tuple[int, int, int, int]:
    """Integer bounding box ``(min_x, min_y, max_x, max_y)`` (pixel-corner) of features ``(N, 2)``.

    ``px`` is in OpenCV pixels; the box is clipped to the image ``[0, width - 1] x [0, height - 1]``.
    """
    pts = np.asarray(px, dtype=np.float64).reshape(-1, 2) + PIXEL_CORNER_OFFSET
    if len(pts) == 0:
        raise ValueError("no feature positions to define the calibrated area")
    lo = np.clip(np.floor(pts.min(axis=0)), 0, [width - 1, height - 1]).astype(int)
    hi = np.clip(np.floor(pts.max(axis=0)), 0, [width - 1, height - 1]).astype(int)
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


def tangent_basis(v: torch.Tensor) -> torch.Tensor:
    """Tangent vectors ``(t1, t2)`` of unit directions ``v (..., 3)`` -> ``(..., 2, 3)``.

    ``t1 = normalize(v x e)`` with ``e = (1, 0, 0)``, or ``(0, 1, 0)`` when ``|v_x| > 0.9``;
    ``t2 = v x t1`` (unit, since ``v`` and ``t1`` are orthonormal).
    """
    ex = torch.zeros_like(v)
    use_y = v[..., 0].abs() > 0.9
    ex[..., 0] = torch.where(use_y, 0.0, 1.0).to(v.dtype)
    ex[..., 1] = torch.where(use_y, 1.0, 0.0).to(v.dtype)
    t1 = torch.linalg.cross(v, ex, dim=-1)
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    t2 = torch.linalg.cross(v, t1, dim=-1)
    return torch.stack([t1, t2], dim=-2)


def _basis(t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform cubic B-spline weights of nodes ``i-1 .. i+2`` at ``t in [0, 1]``: ``(N, 4)`` and d/dt."""
    t2 = t * t
    t3 = t2 * t
    s = 1.0 - t
    w = torch.stack([s * s * s, 3 * t3 - 6 * t2 + 4, -3 * t3 + 3 * t2 + 3 * t + 1, t3], -1) / 6.0
    dw = torch.stack([-3 * s * s, 9 * t2 - 12 * t, -9 * t2 + 6 * t + 3, 3 * t2], -1) / 6.0
    return w, dw


@dataclass(frozen=True)
class SplineEval:
    """A B-spline evaluation at ``N`` pixels.

    Attributes:
        s: ``(N, 3)`` raw spline value.
        d: ``(N, 3)`` unit direction ``s / |s|``.
        norm: ``(N,)`` ``|s|``.
        dd_du: ``(N, 3, 2)`` derivative of ``d`` w.r.t. the (OpenCV) pixel (1/px).
        nodes: ``(N, 16)`` flat node indices ``r GW + c`` of the supporting 4 x 4 nodes.
        weights: ``(N, 16)`` their B-spline weights.
    """

    s: torch.Tensor
    d: torch.Tensor
    norm: torch.Tensor
    dd_du: torch.Tensor
    nodes: torch.Tensor
    weights: torch.Tensor


@dataclass(frozen=True)
class GridSpline:
    """The model's geometry in torch: grid ``(GH, GW, 3)`` and the pixel-to-grid map.

    ``scale`` ``(2,)`` grid units per px and ``offset`` ``(2,)`` such that
    ``g = offset + scale * u`` for OpenCV pixels ``u``; ``lo``/``hi`` ``(2,)`` the clamp box of
    projections in OpenCV pixels.
    """

    grid: torch.Tensor
    scale: torch.Tensor
    offset: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor

    @property
    def shape(self) -> tuple[int, int]:
        """``(GH, GW)``."""
        return int(self.grid.shape[0]), int(self.grid.shape[1])

    def with_grid(self, grid: torch.Tensor) -> GridSpline:
        """The same map with another grid of the same shape."""
        return GridSpline(grid, self.scale, self.offset, self.lo, self.hi)

    def evaluate(self, u: torch.Tensor) -> SplineEval:
        """Unproject OpenCV pixels ``u (N, 2)`` (inside the area) with derivatives."""
        gh, gw = self.shape
        g = self.offset + self.scale * u
        upper = torch.tensor([gw - 3, gh - 3], device=u.device)
        base = torch.minimum(torch.clamp(torch.floor(g), min=1).long(), upper)
        t = g - base.to(g.dtype)
        wx, dwx = _basis(t[:, 0])
        wy, dwy = _basis(t[:, 1])
        offs = torch.arange(-1, 3, device=u.device)
        cols = base[:, 0:1] + offs
        rows = base[:, 1:2] + offs
        nodes = (rows[:, :, None] * gw + cols[:, None, :]).reshape(-1, 16)
        v = self.grid.reshape(-1, 3)[nodes].reshape(-1, 4, 4, 3)
        w = (wy[:, :, None] * wx[:, None, :]).reshape(-1, 16)
        rows_x = torch.stack([wx, dwx], 1)[:, None] @ v  # (N, 4, 2, 3): sum over columns
        both = torch.stack([wy, dwy], 1) @ rows_x.reshape(-1, 4, 6)  # (N, 2, 6): sum over rows
        s = both[:, 0, :3]
        ds_du = torch.stack([both[:, 0, 3:] * self.scale[0], both[:, 1, :3] * self.scale[1]], dim=-1)
        norm = s.norm(dim=-1)
        d = s / norm[:, None]
        proj = torch.eye(3, dtype=s.dtype, device=s.device) - d[:, :, None] * d[:, None, :]
        dd_du = proj @ ds_du / norm[:, None, None]
        return SplineEval(s, d, norm, dd_du, nodes, w)

    def clamp(self, u: torch.Tensor) -> torch.Tensor:
        """Clamp OpenCV pixels ``(N, 2)`` to the calibrated area."""
        return torch.maximum(torch.minimum(u, self.hi), self.lo)

    def start_pixels(self, directions: torch.Tensor, samples: int = 24) -> torch.Tensor:
        """Initial guesses for projecting unit ``directions (N, 3)``: the best of a pixel lattice."""
        ax = [torch.linspace(float(self.lo[i]), float(self.hi[i]), samples, dtype=directions.dtype,
                             device=directions.device) for i in range(2)]
        yy, xx = torch.meshgrid(ax[1], ax[0], indexing="ij")
        lattice = torch.stack([xx.reshape(-1), yy.reshape(-1)], -1)
        rays = self.evaluate(lattice).d
        best = torch.argmax(directions @ rays.T, dim=1)
        return lattice[best]

    def project(self, points: torch.Tensor, init: torch.Tensor | None = None,
                iterations: int = 100, tol_px: float = 1e-8) -> tuple[torch.Tensor, torch.Tensor]:
        """Project camera-frame points ``(N, 3)`` to OpenCV pixels ``(N, 2)``.

        Levenberg-Marquardt (:func:`blurcalib.optim.lm.run_batch` on
        :class:`blurcalib.camera.spline_projection.SplineProjection`) on ``|d(u) - p / |p||^2`` per
        point, at most ``iterations`` trials (initial lambda 0.5 % of the diagonal from the lattice
        start, :data:`_WARM_DAMPING` from ``init``; /2 on success, x4 on failure), clamped to the
        calibrated area (a point held at its edge for several iterations is given up), started from
        ``init`` ``(N, 2)`` (a previous projection) or from the best pixel of a lattice. A point
        whose next step is below ``tol_px`` takes it and stops, its residual there linearised
        (``r - D step``) instead of evaluated: a warm-started projection then costs two
        evaluations instead of three.
        Returns the pixels and ``inside (N,)``: converged strictly inside the area (a clamped
        projection means the point is outside the calibrated field of view).
        """
        p = points / points.norm(dim=-1, keepdim=True)
        start = self.clamp(init.clone() if init is not None else self.start_pixels(p))
        fit = SplineProjection(self, p, start, tol_px, _EDGE_ITERATIONS)
        lam = (0.005 if init is None else _WARM_DAMPING) * (fit.D * fit.D).sum(dim=(1, 2))
        run_batch(fit, LmRule(PROJECTION_DAMPING, Stopping(max_trials=iterations)), lam)
        u, cost = fit.u, fit.cost
        inside = torch.all((u > self.lo) & (u < self.hi), dim=-1) & (cost < 1e-16)
        return u, inside



def projection_jacobians(spline: GridSpline, u: torch.Tensor, points: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Derivatives of the projection ``u = pi(p)`` at its solution, by implicit differentiation.

    At the solution ``d(u, theta) = p / |p|``. Differentiating, with ``D_u = dd/du (3, 2)``
    (tangent to the sphere at ``d``) and ``A = (D_u^T D_u)^-1``::

        du/dp       = A D_u^T (I - n n^T) / |p| = A D_u^T / |p|                      (2, 3)
        du/d(a, b)_k = -A D_u^T w_k [t1_k t2_k] / |s|                                  (2, 2)

    for each of the 16 supporting nodes ``k`` (weight ``w_k``, tangents ``t1_k, t2_k``).

    Args:
        spline: the model.
        u: ``(N, 2)`` projections (OpenCV px) of ``points``.
        points: ``(N, 3)`` camera-frame points (m).
    Returns:
        ``J_p (N, 2, 3)`` px/m, ``J_grid (N, 2, 32)`` px per tangent unit (columns
        ``2 j + {0, 1}`` for node ``nodes[:, j]``), ``nodes (N, 16)``.
    """
    ev = spline.evaluate(u)
    D = ev.dd_du
    H = D.transpose(1, 2) @ D
    A = torch.linalg.inv(H)
    AD = A @ D.transpose(1, 2)
    J_p = AD / points.norm(dim=-1)[:, None, None]
    tang = tangent_basis(spline.grid.reshape(-1, 3))[ev.nodes]
    wt = ev.weights[:, :, None, None] * tang / ev.norm[:, None, None, None]
    J_grid = -torch.einsum("nic,nkjc->nikj", AD, wt).reshape(-1, 2, 32)
    return J_p, J_grid, ev.nodes


def param_columns(nodes: torch.Tensor) -> torch.Tensor:
    """Grid parameter columns ``(N, 32)`` (``2 k, 2 k + 1`` per node) of node indices ``(N, 16)``."""
    return (2 * nodes[:, :, None] + torch.arange(2, device=nodes.device)).reshape(len(nodes), -1)


def accumulate_blocks(H: torch.Tensor, cols: torch.Tensor, blocks: torch.Tensor,
                      chunk: int = 4096) -> None:
    """``H[cols_i, cols_i] += blocks_i`` for every row ``i`` (``cols (N, m)``, ``blocks (N, m, m)``).

    Done in chunks of ``chunk`` rows so the scattered index arrays stay small.
    """
    n = H.shape[1]
    flat = H.view(-1)
    for i in range(0, len(cols), chunk):
        c = cols[i:i + chunk]
        idx = (c[:, :, None] * n + c[:, None, :]).reshape(-1)
        flat.index_add_(0, idx, blocks[i:i + chunk].reshape(-1))


def apply_update(grid: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """``v <- normalize(v + a t1 + b t2)`` for ``delta (GH, GW, 2)``; returns the new grid."""
    t = tangent_basis(grid)
    new = grid + delta[..., 0:1] * t[..., 0, :] + delta[..., 1:2] * t[..., 1, :]
    return cast(torch.Tensor, new / new.norm(dim=-1, keepdim=True))


@dataclass(frozen=True, eq=False)
class CentralGeneric:
    """The reference tool's ``CentralGenericModel``.

    Attributes:
        width, height: image size (px).
        min_x, min_y, max_x, max_y: calibrated area ``[min, max + 1)`` (integer, pixel-corner
            convention, as in the reference tool's files).
        grid: ``(GH, GW, 3)`` float64 unit direction vectors, rows top to bottom.
    """

    width: int
    height: int
    min_x: int
    min_y: int
    max_x: int
    max_y: int
    grid: np.ndarray

    def __post_init__(self) -> None:
        grid = np.array(self.grid, dtype=np.float64)
        if grid.ndim != 3 or grid.shape[2] != 3 or grid.shape[0] < 4 or grid.shape[1] < 4:
            raise ValueError(f"grid must have shape (GH >= 4, GW >= 4, 3), got {grid.shape}")
        norms = np.linalg.norm(grid, axis=-1, keepdims=True)
        if not np.all(np.isfinite(grid)) or np.any(norms == 0):
            raise ValueError("grid contains non-finite or zero vectors")
        grid = grid / norms
        grid.setflags(write=False)
        object.__setattr__(self, "grid", grid)
        if not (self.max_x >= self.min_x and self.max_y >= self.min_y):
            raise ValueError(f"empty calibrated area x {self.min_x}..{self.max_x}, "
                             f"y {self.min_y}..{self.max_y}")

    @property
    def grid_width(self) -> int:
        return int(self.grid.shape[1])

    @property
    def grid_height(self) -> int:
        return int(self.grid.shape[0])

    @property
    def area_opencv(self) -> tuple[float, float, float, float]:
        """Calibrated area ``(x0, y0, x1, y1)`` in OpenCV pixels: ``[x0, x1) x [y0, y1)``."""
        o = PIXEL_CORNER_OFFSET
        return self.min_x - o, self.min_y - o, self.max_x + 1 - o, self.max_y + 1 - o

    def spline(self, device: torch.device | str = "cpu") -> GridSpline:
        """The torch form of the model (float64 on ``device``)."""
        kw: dict[str, Any] = {"dtype": torch.float64, "device": device}
        sx = (self.grid_width - 3) / (self.max_x + 1 - self.min_x)
        sy = (self.grid_height - 3) / (self.max_y + 1 - self.min_y)
        scale = torch.tensor([sx, sy], **kw)
        o = PIXEL_CORNER_OFFSET
        offset = torch.tensor([1 + sx * (o - self.min_x), 1 + sy * (o - self.min_y)], **kw)
        lo = torch.tensor([self.min_x - o, self.min_y - o], **kw)
        hi = torch.tensor([self.max_x + _AREA_EDGE - o, self.max_y + _AREA_EDGE - o], **kw)
        return GridSpline(torch.tensor(self.grid, **kw), scale, offset, lo, hi)

    def with_grid(self, grid: ArrayLike) -> CentralGeneric:
        """The same model with another grid of the same shape."""
        grid = np.asarray(grid, dtype=np.float64)
        if grid.shape != self.grid.shape:
            raise ValueError(f"grid shape {grid.shape} differs from {self.grid.shape}")
        return CentralGeneric(self.width, self.height, self.min_x, self.min_y, self.max_x,
                              self.max_y, grid)

    def to_grid(self, px: ArrayLike) -> np.ndarray:
        """OpenCV pixels ``(N, 2)`` -> grid coordinates ``(N, 2)``."""
        sp = self.spline()
        u = torch.as_tensor(np.asarray(px, dtype=np.float64).reshape(-1, 2))
        return (sp.offset + sp.scale * u).numpy()

    def in_area(self, px: ArrayLike) -> np.ndarray:
        """``(N,)`` bool: OpenCV pixels ``(N, 2)`` inside the calibrated area."""
        x0, y0, x1, y1 = self.area_opencv
        p = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        return (p[:, 0] >= x0) & (p[:, 0] < x1) & (p[:, 1] >= y0) & (p[:, 1] < y1)

    def pixel_to_ray(self, px: ArrayLike) -> np.ndarray:
        """OpenCV pixels ``(N, 2)`` -> unit viewing directions ``(N, 3)``; NaN outside the area."""
        p = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        out = np.full((len(p), 3), np.nan)
        ok = self.in_area(p)
        if ok.any():
            out[ok] = self.spline().evaluate(torch.as_tensor(p[ok])).d.numpy()
        return out

    def project(self, points_cam: ArrayLike, init: ArrayLike | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points ``(N, 3)`` -> OpenCV pixels ``(N, 2)`` and ``inside (N,)`` bool.

        Points whose ray leaves the calibrated area get the clamped pixel and ``inside`` False.
        """
        return self.project_valid(points_cam, init)

    def project_valid(self, points_cam: ArrayLike, init: ArrayLike | None = None, tol_px: float = 1e-8
                      ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`project` solved to ``tol_px`` (the interface of
        :class:`blurcalib.camera.remap.RayProjector`)."""
        pts = torch.as_tensor(np.asarray(points_cam, dtype=np.float64).reshape(-1, 3))
        start = None if init is None else torch.as_tensor(np.asarray(init, np.float64).reshape(-1, 2))
        u, inside = self.spline().project(pts, start, tol_px=tol_px)
        return u.numpy(), inside.numpy()

    def rotated(self, R: ArrayLike) -> CentralGeneric:
        """The model whose directions are ``R v`` (a change of the camera frame)."""
        R = np.asarray(R, dtype=np.float64)
        return self.with_grid(self.grid @ R.T)


def best_fit_rotation(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """Rotation ``Q (3, 3)`` minimising ``sum |Q a_i - b_i|^2`` over unit vectors ``a, b (N, 3)``
    (Kabsch). A central camera's orientation is a gauge: two models are compared after it."""
    U, _, Vt = np.linalg.svd(np.asarray(b, dtype=np.float64).T @ np.asarray(a, dtype=np.float64))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return cast(np.ndarray, U @ D @ Vt)


def _lattice(x0: float, y0: float, x1: float, y1: float, step: float) -> np.ndarray:
    nx = max(2, math.ceil((x1 - x0) / step) + 1)
    ny = max(2, math.ceil((y1 - y0) / step) + 1)
    xs = np.linspace(x0, x1, nx)
    ys = np.linspace(y0, y1, ny)
    xx, yy = np.meshgrid(xs, ys)
    return np.column_stack([xx.ravel(), yy.ravel()])


def fit_to_rays(pixel_to_ray: Callable[[np.ndarray], np.ndarray], width: int, height: int,
                area: tuple[int, int, int, int] | None = None, cell_px: float = DEFAULT_CELL_PX,
                grid_shape: tuple[int, int] | None = None, samples_per_cell: int = 4,
                iterations: int = 4) -> CentralGeneric:
    """A generic model reproducing another camera's rays over the calibrated area.

    Least squares on a dense pixel sample (``samples_per_cell`` per cell and axis, border
    included): first linear in the raw node vectors (``s(u) ~ r(u)``), then Gauss-Newton on the
    normalised directions ``d(u) - r(u)`` in the nodes' tangent parameters.

    Args:
        pixel_to_ray: OpenCV pixels ``(N, 2)`` -> unit rays ``(N, 3)`` (e.g.
            ``BrownConrady.pixel_to_ray``).
        width, height: image size (px).
        area: ``(min_x, min_y, max_x, max_y)`` pixel-corner; default the whole image.
        cell_px: grid cell length (px) when ``grid_shape`` is not given.
        grid_shape: ``(GH, GW)`` nodes.
    """
    if area is None:
        area = (0, 0, width - 1, height - 1)
    min_x, min_y, max_x, max_y = area
    if grid_shape is None:
        grid_shape = (grid_size_for(max_y + 1 - min_y, cell_px), grid_size_for(max_x + 1 - min_x, cell_px))
    gh, gw = grid_shape
    proto = CentralGeneric(width, height, min_x, min_y, max_x, max_y,
                           np.broadcast_to([0.0, 0.0, 1.0], (gh, gw, 3)))
    x0, y0, x1, y1 = proto.area_opencv
    step = min((x1 - x0) / (gw - 3), (y1 - y0) / (gh - 3)) / samples_per_cell
    px = _lattice(x0, y0, x1 - 1e-6, y1 - 1e-6, step)
    rays = np.asarray(pixel_to_ray(px), dtype=np.float64)
    rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    sp = proto.spline()
    u = torch.as_tensor(px)
    target = torch.as_tensor(rays)
    ev = sp.evaluate(u)
    n = gh * gw
    BtB = torch.zeros(n, n, dtype=torch.float64)
    accumulate_blocks(BtB, ev.nodes, ev.weights[:, :, None] * ev.weights[:, None, :])
    Btr = torch.zeros(n, 3, dtype=torch.float64).index_add_(
        0, ev.nodes.reshape(-1), (ev.weights[:, :, None] * target[:, None, :]).reshape(-1, 3))
    V = torch.as_tensor(_solve_banded_spd(BtB.numpy(), Btr.numpy(), bandwidth=3 * gw + 3, ridge=1e-9))
    grid = (V / V.norm(dim=1, keepdim=True)).reshape(gh, gw, 3)
    for _ in range(iterations):
        sp = sp.with_grid(grid)
        ev = sp.evaluate(u)
        r = ev.d - target
        proj = torch.eye(3, dtype=torch.float64) - ev.d[:, :, None] * ev.d[:, None, :]
        tang = tangent_basis(grid.reshape(-1, 3))[ev.nodes]
        Jk = torch.einsum("nab,nkjb->nakj", proj, tang) * (ev.weights / ev.norm[:, None])[:, None, :, None]
        Jk = Jk.reshape(len(px), 3, 32)
        cols = param_columns(ev.nodes)
        H = torch.zeros(2 * n, 2 * n, dtype=torch.float64)
        accumulate_blocks(H, cols, Jk.transpose(1, 2) @ Jk)
        g = torch.zeros(2 * n, dtype=torch.float64).index_add_(
            0, cols.reshape(-1), (Jk.transpose(1, 2) @ r[:, :, None]).reshape(-1))
        H.diagonal().add_(1e-12)
        delta = torch.cholesky_solve(-g[:, None], torch.linalg.cholesky(H)).squeeze(1)
        grid = apply_update(grid, delta.reshape(gh, gw, 2))
        if float(delta.abs().max()) < 1e-10:
            break
    return proto.with_grid(grid.numpy())


def _solve_banded_spd(A: np.ndarray, b: np.ndarray, bandwidth: int, ridge: float) -> np.ndarray:
    """``(A + ridge I)^-1 b`` for a symmetric positive (semi-)definite ``A (n, n)`` whose entries vanish
    more than ``bandwidth`` off the diagonal (the B-spline normal matrix: nodes couple within 3
    rows and columns of the grid, ``3 GW + 3``), by a banded Cholesky factorisation: ``O(n w^2)``
    instead of a dense ``O(n^3)`` solve."""
    n = len(A)
    w = min(bandwidth, n - 1)
    band = np.zeros((w + 1, n))
    for k in range(w + 1):
        band[k, :n - k] = np.diagonal(A, -k)
    band[0] += ridge
    return cast(np.ndarray, scipy.linalg.solveh_banded(band, b, lower=True))


def undistortion_map(model: CentralGeneric, fx: float, fy: float, cx: float, cy: float,
                     width: int | None = None, height: int | None = None, coarse_px: int = 16
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Maps for ``cv2.remap`` from the generic camera's image to a pinhole camera's.

    The pinhole camera ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (OpenCV pixels, same camera
    frame) of ``width x height`` px (default the model's): pixel ``(x, y)`` of the output looks
    along ``((x - cx) / fx, (y - cy) / fy, 1)``. :func:`blurcalib.camera.remap.output_maps` with a
    pinhole output: -1 where the ray leaves the calibrated area.
    """
    output = OutputProjection("pinhole", fx, fy, cx, cy, model.width if width is None else width,
                              model.height if height is None else height)
    return output_maps(model, output, coarse_px)
