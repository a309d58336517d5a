"""Projection uncertainty of the generic camera, the cross-validation diff and capture guidance.

Projection uncertainty (docs/uncertainty.md gives the derivation). The bundle adjustment
(:mod:`blurcalib.calib.bundle`) minimises ``sum_i W_i |r_i|^2 + priors`` in px^2. With the
observations' noise ``N(0, sigma^2 / W_i)`` per axis, the information on the grid parameters,
the per-frame blocks (pose and shift) marginalised by the Schur complement, is::

    H_ff = H_ff,data / sigma^2 + H_ff,prior                                (F, 8, 8)
    A    = (H_gg,data - H_gf,data H_ff'^-1 H_gf,data^T) / sigma^2 + H_gg,prior     (G, G)

with ``H_ff' = H_ff,data + sigma^2 H_ff,prior``: the reduced camera system at the solution, no
damping, the priors (costs in px^2) keeping their own weights (``H_gg,prior`` divided by
``prior_scale^2``, 1 by default). The data cannot see a common
rotation of the grid and the poses (a central camera's gauge): ``A g = H_gg,prior g`` for the
three grid directions ``g`` of an infinitesimal rotation. The rotation is marginalised too
(``A_m = A - A_pg (g^T H_gg,prior g)^-1 A_pg^T`` with ``A_pg = H_gg,prior g``, orthonormal
``g``), and the covariance of the grid is ``Sigma = (A_m + k g g^T)^-1`` (any ``k > 0``: every
quantity below is blind to ``g``).

``sigma`` (``noise_px``) is the IRLS-weighted residual scale::

    sigma^2 = sum_i W_i |r_i|^2 / (2 N - p),   p = 6 F + 2 F_shift + (G - 3 - tr(H_m Sigma))

``p`` is the effective number of parameters (the trace of the hat matrix): poses and free
shifts, plus the grid directions the data determine (``H_m`` the smoothness prior with the
rotation marginalised; the prior-determined directions do not count). ``p`` is evaluated at a
first estimate of ``sigma`` (``p`` counting every grid parameter an observation touches) and
``Sigma`` is then scaled by the ratio of the two estimates of ``sigma^2`` (exact where the data
determine the grid).

Meaning. ``Sigma`` is the posterior covariance when ``prior_scale * smoothness_px`` is the real
spread of the initial camera's second differences. The bundle adjustment weighs its
prior against unit-weight residuals, i.e. ``1 / sigma^2`` times more strongly than that, so in
the directions the data hardly determine (cells without observations, the focal-scale mode of
few frames) its camera stays at the initial camera, and there ``sigma_px`` is the prior's
spread: an upper bound when the initial camera is better than that.

Propagation to pixels. At lattice pixel ``u_k`` the ray is ``d_k = d(u_k; theta)``; a grid
perturbation ``dtheta`` moves it by ``M_k dtheta`` (``M_k = (I - d d^T) sum_j w_j T_j^T / |s|``)
and the pixel that sees the same ray by ``-D_k^+ M_k dtheta`` (``D_k = dd/du``, ``D^+ = (D^T
D)^-1 D^T``). As the comparison with a true camera does, the best-fit rotation ``omega`` of the
rays over the whole lattice is removed: ``omega = N^-1 sum_k [d_k]_x M_k dtheta = L dtheta``
with ``N = sum_k (I - d_k d_k^T)``, so the pixel error is
``e_k = (J_k + R_k L) dtheta`` with ``J_k = -D_k^+ M_k`` and ``R_k = -D_k^+ [d_k]_x``, and::

    C_k = J_k Sigma J_k^T + J_k Sigma L^T R_k^T + R_k L Sigma J_k^T + R_k L Sigma L^T R_k^T   (2, 2) px^2

``sigma_px = sqrt(tr C_k)``. All of it is batched in torch float64 on the bundle adjustment's
device.

Cross-validation diff: two generic cameras (e.g. of two halves of the frames) compared over their
common calibrated area after the best-fit rotation of their rays. For independent halves of
equal size the expected squared diff is about ``4 sigma_px^2`` of the camera of all frames.

Pixels: OpenCV convention (the centre of the top-left pixel is ``(0, 0)``) everywhere.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from matplotlib import colors
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.image import AxesImage
from scipy.interpolate import RegularGridInterpolator

from blurcalib.calib.bundle import BundleResult, reduce_frames
from blurcalib.calib.normal_equations import NormalEquations, normal_equations
from blurcalib.camera.generic import CentralGeneric, GridSpline, SplineEval, best_fit_rotation, tangent_basis
from blurcalib.geometry.lie import skew
from blurcalib.io.atomic import atomic_path

__all__ = [
    "CrossValidationDiff",
    "ProjectionUncertainty",
    "cross_validation_diff",
    "grid_covariance",
    "guidance",
    "projection_uncertainty",
    "save_uncertainty_npz",
    "save_uncertainty_png",
]

BORDER_PX = 64.0
"""Width of the image's border band (px from the edge), as in ``blurcalib experiment generic``."""

_REGIONS = {
    (0, 0): "in the top-left corner", (0, 1): "at the top edge", (0, 2): "in the top-right corner",
    (1, 0): "at the left edge", (1, 1): "in the centre", (1, 2): "at the right edge",
    (2, 0): "in the bottom-left corner", (2, 1): "at the bottom edge", (2, 2): "in the bottom-right corner",
}


def _lattice(x0: float, y0: float, x1: float, y1: float, step_px: float
             ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Pixel centres every ``<= step_px`` px from ``x0 + 0.5`` to ``x1 - 0.5`` (area ``[x0, x1)``)."""
    if not step_px > 0:
        raise ValueError(f"step_px must be positive, got {step_px}")
    xa, xb, ya, yb = x0 + 0.5, x1 - 0.5, y0 + 0.5, y1 - 0.5
    nx = max(2, math.ceil((xb - xa) / step_px) + 1)
    ny = max(2, math.ceil((yb - ya) / step_px) + 1)
    xx, yy = np.meshgrid(np.linspace(xa, xb, nx), np.linspace(ya, yb, ny))
    return xx.ravel(), yy.ravel(), (ny, nx)


def _edge_distance(x: np.ndarray, y: np.ndarray, width: int, height: int) -> np.ndarray:
    """Distance (px) of OpenCV pixels to the nearest image edge."""
    return cast(np.ndarray, np.minimum.reduce([x + 0.5, y + 0.5, width - 0.5 - x, height - 0.5 - y]))


@dataclass(eq=False)
class ProjectionUncertainty:
    """1-sigma projection uncertainty of a generic camera on a pixel lattice over its calibrated area.

    Attributes:
        x, y: ``(K,)`` px, OpenCV convention; ``x.reshape(shape)`` is the lattice (rows top to
            bottom), steps at most the requested ``step_px``.
        shape: ``(ny, nx)``.
        sigma_px: ``(K,)`` px, ``sqrt(tr C_k)`` of the 2 x 2 covariance (global rotation removed).
        cov: ``(K, 2, 2)`` px^2.
        noise_px: per-axis noise of a unit-weight observation, estimated from the inlier
            residuals (or given).
        width, height: image size (px).
        effective_parameters: ``p`` of the noise estimate (poses, free shifts and the grid
            directions the data determine).
        scale_px: 1-sigma of the error field's focal-scale part: the mean of the diagonal of its
            best-fit affine part times the image centre-to-corner distance (px), as
            :func:`blurcalib.sim.evaluate.camera_accuracy`'s ``scale_px``.
        noise_free_px: the per-axis noise of the observations of frames with a free shift
            (blurry frames), estimated apart from the others' (``noise_px``); equal to it with
            one group or a given ``noise_px``.
    """

    x: np.ndarray = field(repr=False)
    y: np.ndarray = field(repr=False)
    shape: tuple[int, int]
    sigma_px: np.ndarray = field(repr=False)
    cov: np.ndarray = field(repr=False)
    noise_px: float
    width: int
    height: int
    effective_parameters: float
    scale_px: float
    noise_free_px: float

    def median(self) -> float:
        """Median ``sigma_px`` over the lattice (px)."""
        return float(np.nanmedian(self.sigma_px))

    def rms(self) -> float:
        """Root mean square of ``sigma_px`` over the lattice (px)."""
        return float(np.sqrt(np.nanmean(self.sigma_px ** 2)))

    def border_band(self, width_px: float = BORDER_PX) -> float:
        """RMS ``sigma_px`` over the lattice pixels within ``width_px`` of the image edge (px);
        NaN when the calibrated area does not reach the band."""
        band = _edge_distance(self.x, self.y, self.width, self.height) < width_px
        if not band.any():
            return float("nan")
        return float(np.sqrt(np.nanmean(self.sigma_px[band] ** 2)))

    def at(self, px: np.ndarray) -> np.ndarray:
        """``sigma_px`` bilinearly interpolated at OpenCV pixels ``(N, 2)``; NaN outside the lattice."""
        xs = self.x.reshape(self.shape)[0]
        ys = self.y.reshape(self.shape)[:, 0]
        interp = RegularGridInterpolator((ys, xs), self.sigma_px.reshape(self.shape),
                                         bounds_error=False, fill_value=np.nan)
        p = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        return cast(np.ndarray, interp(p[:, ::-1]))


def _rotation_directions(grid: torch.Tensor) -> torch.Tensor:
    """``(G, 3)``: the grid parameters of an infinitesimal rotation ``omega`` of every node.

    Node ``v`` moves by ``omega x v``; its tangent parameters are ``t_j . (omega x v) =
    omega . (v x t_j)``.
    """
    v = grid.reshape(-1, 3)
    t = tangent_basis(v)
    return cast(torch.Tensor, torch.linalg.cross(v[:, None, :].expand_as(t), t, dim=-1).reshape(-1, 3))


def _grid_information(ne: NormalEquations, prior: torch.Tensor, noise_sq: float) -> torch.Tensor:
    """``A (G, G)``: the grid's information with the per-frame blocks marginalised (Schur), the
    smoothness prior's Hessian ``prior (G, G)``; its lower triangle (all that
    :func:`_gauge_marginalised`'s Cholesky factorisation reads)."""
    eye8 = torch.eye(8, dtype=ne.hff_data.dtype, device=ne.hff_data.device)
    Hff = ne.hff_data + noise_sq * ne.hff_prior + 1e-12 * eye8  # a frame without inliers stays regular
    A, _ = reduce_frames(ne.hgg_data, ne.hgf_data, torch.cholesky_inverse(torch.linalg.cholesky(Hff)),
                         lower=True)
    return A.div_(noise_sq).add_(prior)


def _gauge_marginalised(A: torch.Tensor, prior: torch.Tensor, g: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """``Sigma = (A_m + k g g^T)^-1`` and the prior with the rotation marginalised, ``H_m`` (module
    docstring; formed in ``prior``'s storage); ``g (G, 3)`` orthonormal, ``A``'s lower triangle read."""
    C = prior @ g
    B = g.T @ C
    evals, evecs = torch.linalg.eigh(0.5 * (B + B.T))
    keep = evals > 1e-12 * float(evals.abs().max().clamp_min(1e-300))
    B_pinv = (evecs[:, keep] / evals[keep]) @ evecs[:, keep].T
    coupling = C @ B_pinv @ C.T
    k = float(torch.diagonal(A).mean())
    Am = torch.sub(A, coupling).addmm_(g, g.T, alpha=k)
    Am.diagonal().add_(1e-12 * k)  # as the bundle adjustment's solver
    Sigma = torch.cholesky_inverse(torch.linalg.cholesky(Am))
    del Am
    return Sigma, prior.sub_(coupling)


def projection_uncertainty(result: BundleResult, step_px: float = 16.0, noise_px: float | None = None,
                           prior_scale: float = 1.0) -> ProjectionUncertainty:
    """The generic camera's 1-sigma projection uncertainty over its calibrated area (module docstring).

    Args:
        result: a :func:`blurcalib.calib.bundle.bundle_adjust` result (its ``data`` holds the
            observations); computed on its device.
        step_px: lattice step at most (px).
        noise_px: per-axis noise of a unit-weight observation (px); default: estimated from the
            inlier residuals.
        prior_scale: the spread of the initial camera's second differences in units of the
            smoothness prior's ``smoothness_px`` (the prior's information is divided by its
            square); 1 takes the prior at its own weight. Smaller values trust the initial
            camera more where the data do not determine the grid (docs/uncertainty.md).

    Raises:
        ValueError: a non-positive ``step_px``, ``noise_px`` or ``prior_scale``, or fewer
            residuals than parameters.
    """
    if noise_px is not None and not noise_px > 0:
        raise ValueError(f"noise_px must be positive, got {noise_px}")
    if not prior_scale > 0:
        raise ValueError(f"prior_scale must be positive, got {prior_scale}")
    model = result.model
    Sigma, noise_sq, p_eff, shift_noise = _grid_sigma(result, noise_px, prior_scale)
    spline = model.spline(Sigma.device)
    x, y, shape = _lattice(*model.area_opencv, step_px)
    corner = np.array([model.width - 1, model.height - 1]) / 2.0
    lattice = torch.as_tensor(np.column_stack([x, y]), dtype=torch.float64, device=Sigma.device)
    cov, scale_var = _pixel_covariance(spline, Sigma, lattice, corner)
    sigma = np.sqrt(np.clip(np.trace(cov, axis1=1, axis2=2), 0.0, None))
    return ProjectionUncertainty(x, y, shape, sigma, cov, math.sqrt(noise_sq), model.width, model.height,
                                 p_eff, math.sqrt(max(scale_var, 0.0)), math.sqrt(noise_sq) * shift_noise)


def _grid_sigma(result: BundleResult, noise_px: float | None, prior_scale: float
                ) -> tuple[torch.Tensor, float, float, float]:
    """``Sigma (G, G)`` (module docstring), the noise variance ``sigma^2`` (px^2), the effective
    parameter count ``p`` and the blurry frames' noise over the sharp frames' (1 with a given
    ``noise_px``)."""
    shift_noise = 1.0
    if noise_px is None:
        result, shift_noise = _group_weighted(result)
    ne = normal_equations(result)
    prior = ne.hgg_prior / prior_scale ** 2
    spline = result.model.spline(ne.hgg_data.device)
    G, F = ne.hgf_data.shape[:2]
    free = int(np.count_nonzero(result.data.shift_free))
    g, _ = torch.linalg.qr(_rotation_directions(spline.grid))
    residuals = 2 * ne.observations
    fixed_p = 6 * F + 2 * free
    if residuals <= fixed_p + 3:
        raise ValueError(f"{ne.observations} observations cannot determine {F} poses and the camera")
    observed_p = int((torch.diagonal(ne.hgg_data) > 0).sum()) - 3
    noise_sq = (noise_px ** 2 if noise_px is not None
                else ne.weighted_sq / max(residuals - fixed_p - observed_p, ne.observations))
    Sigma, prior_m = _gauge_marginalised(_grid_information(ne, prior, noise_sq), prior, g)
    p_eff = fixed_p + G - 3 - float((prior_m * Sigma).sum())
    if noise_px is None:
        new_sq = ne.weighted_sq / max(residuals - p_eff, 1.0)
        Sigma.mul_(new_sq / noise_sq)
        noise_sq = new_sq
    return Sigma, noise_sq, p_eff, shift_noise


def _group_weighted(result: BundleResult) -> tuple[BundleResult, float]:
    """``result`` with the observations of frames whose shift is free (blurry frames) weighted by
    ``(sigma_fixed / sigma_free)^2``, their noise relative to the other frames' (each group's
    IRLS-weighted RMS residual), and that ratio ``sigma_free / sigma_fixed`` (1 with one group).

    Blurry features are noisier than sharp ones: one pooled noise level would charge the sharp
    observations with the blurry ones' noise.
    """
    data = result.data
    free = np.asarray(data.shift_free, dtype=bool)[np.asarray(data.frame)]
    ok = result.inlier & (data.weights > 0)
    r2 = np.nansum(result.residuals ** 2, axis=1)
    if not (ok & free).any() or not (ok & ~free).any():
        return result, 1.0
    ratio_sq = (np.sum(data.weights[ok & free] * r2[ok & free]) / np.sum(data.weights[ok & free])
                / (np.sum(data.weights[ok & ~free] * r2[ok & ~free]) / np.sum(data.weights[ok & ~free])))
    weights = np.where(free, data.weights / ratio_sq, data.weights)
    return replace(result, data=replace(data, weights=weights)), math.sqrt(ratio_sq)


def _pixel_covariance(spline: GridSpline, Sigma: torch.Tensor, u: torch.Tensor, corner: np.ndarray
                      ) -> tuple[np.ndarray, float]:
    """``C_k (K, 2, 2)`` px^2 at pixels ``u (K, 2)`` from the grid covariance (module docstring), and
    the variance (px^2) of the error field's focal-scale part at the distance ``|corner|`` from
    the image centre ``corner (2,)`` (:func:`blurcalib.sim.evaluate.camera_accuracy`'s ``scale_px``)."""
    ev = spline.evaluate(u)
    D = ev.dd_du
    Dp = torch.linalg.inv(D.transpose(1, 2) @ D) @ D.transpose(1, 2)  # (K, 2, 3)
    W, cols, dx, L = _ray_derivatives(spline, u, ev)
    J = -Dp @ W
    R = -Dp @ dx
    G = Sigma.shape[0]
    S_kk = Sigma[cols[:, :, None], cols[:, None, :]]  # (K, 32, 32)
    SL = Sigma @ L.T  # (G, 3)
    LSL = L @ SL
    cross = J @ SL[cols] @ R.transpose(1, 2)
    cov = J @ S_kk @ J.transpose(1, 2) + cross + cross.transpose(1, 2) + R @ LSL @ R.transpose(1, 2)
    # focal scale: e ~ a + A (x - centre), scale = (A_xx + A_yy) / 2 |corner| = sum_k c_k . e_k
    centred = u - torch.as_tensor(corner, dtype=u.dtype, device=u.device)
    design = torch.cat([torch.ones_like(u[:, :1]), centred], 1)
    rows = torch.linalg.pinv(design)  # (3, K)
    c = 0.5 * float(np.linalg.norm(corner)) * torch.stack([rows[1], rows[2]], 1)  # (K, 2)
    w = torch.zeros(G, dtype=u.dtype, device=u.device)
    w.index_add_(0, cols.reshape(-1), (c[:, None, :] @ J).reshape(-1))
    w += ((c[:, None, :] @ R).sum(0) @ L).reshape(-1)
    scale_var = float(w @ Sigma @ w)
    return (0.5 * (cov + cov.transpose(1, 2))).cpu().numpy(), scale_var


def _ray_derivatives(spline: GridSpline, u: torch.Tensor, ev: SplineEval | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """At pixels ``u (K, 2)``: ``W (K, 3, 32)`` with ``M_k = (I - d d^T) W_k`` (the spline's
    derivative by its 32 parameters ``cols (K, 32)``; the projection ``(I - d d^T)`` is left to the
    caller, as ``D^+`` and ``[d]_x`` annihilate ``d``), ``[d_k]_x (K, 3, 3)`` and the best-fit
    rotation of the rays ``L (3, G)`` (module docstring); ``ev`` the spline's evaluation at ``u``."""
    ev = spline.evaluate(u) if ev is None else ev
    tang = tangent_basis(spline.grid.reshape(-1, 3))[ev.nodes]  # (K, 16, 2, 3)
    W = torch.einsum("kj,kjcx->kxjc", ev.weights / ev.norm[:, None], tang).reshape(len(u), 3, 32)
    cols = (2 * ev.nodes[:, :, None] + torch.arange(2, device=u.device)).reshape(len(u), 32)
    dx = skew(ev.d)
    eye = torch.eye(3, dtype=u.dtype, device=u.device)
    Nmat = (eye - ev.d[:, :, None] * ev.d[:, None, :]).sum(0)
    Lraw = torch.zeros(3, 2 * spline.grid[..., 0].numel(), dtype=u.dtype, device=u.device)
    Lraw.index_add_(1, cols.reshape(-1), (dx @ W).permute(1, 0, 2).reshape(3, -1))
    return W, cols, dx, torch.linalg.solve(Nmat, Lraw)


def grid_covariance(result: BundleResult, prior_scale: float = 1.0, step_px: float = 16.0) -> torch.Tensor:
    """``(G, G)``: the covariance of the generic camera's grid parameters with the camera's
    rotation removed, ``P Sigma P^T`` with ``P = I - g L`` (module docstring: ``Sigma`` with the
    noise estimated from the residuals and the prior divided by ``prior_scale^2``; ``g (G, 3)``
    the grid directions of a rotation and ``L (3, G)`` the best-fit rotation of the rays over a
    lattice of steps ``<= step_px`` px over the calibrated area, so ``L g = I`` and ``P g = 0``).
    A grid perturbation ``dtheta ~ N(0, P Sigma P^T)`` changes the camera as its error against a
    true camera does, after the best-fit rotation (:func:`blurcalib.sim.evaluate.projection_error_vectors`).

    Raises:
        ValueError: a non-positive ``prior_scale`` or fewer residuals than parameters.
    """
    if not prior_scale > 0:
        raise ValueError(f"prior_scale must be positive, got {prior_scale}")
    Sigma = _grid_sigma(result, None, prior_scale)[0]
    spline = result.model.spline(Sigma.device)
    x, y, _ = _lattice(*result.model.area_opencv, step_px)
    L = _ray_derivatives(spline, torch.as_tensor(np.column_stack([x, y]), dtype=Sigma.dtype,
                                                 device=Sigma.device))[3]
    g = _rotation_directions(spline.grid)
    SL = Sigma @ L.T  # (G, 3)
    return Sigma - g @ SL.T - SL @ g.T + g @ (L @ SL) @ g.T


@dataclass(eq=False)
class CrossValidationDiff:
    """Two generic cameras compared over their common calibrated area (:func:`cross_validation_diff`).

    Attributes:
        x, y: ``(K,)`` px lattice (OpenCV convention); ``shape`` ``(ny, nx)``.
        diff_px: ``(K,)`` px, the distance between a pixel and where camera ``b`` projects camera
            ``a``'s ray of that pixel (best-fit rotation applied); NaN where ``b`` cannot.
        median_px: median of ``diff_px``.
    """

    x: np.ndarray = field(repr=False)
    y: np.ndarray = field(repr=False)
    shape: tuple[int, int]
    diff_px: np.ndarray = field(repr=False)
    median_px: float


def cross_validation_diff(a: CentralGeneric, b: CentralGeneric, step_px: float = 16.0
                          ) -> CrossValidationDiff:
    """Compare two generic cameras of one image size on a lattice over their common area.

    Each lattice pixel's ray in ``a``, turned by the best-fit rotation of ``a``'s rays onto ``b``'s
    over the lattice (a central camera's orientation is a gauge), is projected by ``b``; the diff
    is that projection's distance to the pixel (px).

    Raises:
        ValueError: different image sizes or no common calibrated area.
    """
    if (a.width, a.height) != (b.width, b.height):
        raise ValueError(f"image sizes differ: {a.width} x {a.height} and {b.width} x {b.height}")
    ax0, ay0, ax1, ay1 = a.area_opencv
    bx0, by0, bx1, by1 = b.area_opencv
    x0, y0, x1, y1 = max(ax0, bx0), max(ay0, by0), min(ax1, bx1), min(ay1, by1)
    if x1 - x0 < 2 or y1 - y0 < 2:
        raise ValueError("the two cameras' calibrated areas do not overlap")
    x, y, shape = _lattice(x0, y0, x1, y1, step_px)
    px = np.column_stack([x, y])
    da = a.pixel_to_ray(px)
    db = b.pixel_to_ray(px)
    Q = best_fit_rotation(da, db)
    u, inside = b.project(da @ Q.T, init=px)
    diff = np.linalg.norm(u - px, axis=1)
    diff[~inside] = np.nan
    median = float(np.nanmedian(diff)) if np.isfinite(diff).any() else float("nan")
    return CrossValidationDiff(x, y, shape, diff, median)


def guidance(unc: ProjectionUncertainty, width: int, height: int, threshold_px: float = 0.05) -> list[str]:
    """Plain-words advice on where frames are missing, one line per image region (3 x 3 split).

    A region is named when less than half of it lies in the calibrated area ("... lies outside
    the calibrated area"), or when the 90th percentile of ``sigma_px`` over its lattice pixels
    exceeds ``threshold_px`` (the line gives the region's largest ``sigma_px``). When every
    region exceeds the threshold, one line asks for more frames over the whole image. Lines are
    ordered by the largest uncertainty first; the list is empty when nothing needs more frames.
    """
    if not threshold_px > 0:
        raise ValueError(f"threshold_px must be positive, got {threshold_px}")
    ax0, ax1 = float(unc.x.min()) - 0.5, float(unc.x.max()) + 0.5
    ay0, ay1 = float(unc.y.min()) - 0.5, float(unc.y.max()) + 0.5
    ry = np.clip(((unc.y + 0.5) * 3 // height).astype(int), 0, 2)
    rx = np.clip(((unc.x + 0.5) * 3 // width).astype(int), 0, 2)
    outside: list[str] = []
    high: list[tuple[float, str]] = []
    for (by, bx), where in _REGIONS.items():
        x0, x1 = bx * width / 3 - 0.5, (bx + 1) * width / 3 - 0.5
        y0, y1 = by * height / 3 - 0.5, (by + 1) * height / 3 - 0.5
        covered = (max(0.0, min(x1, ax1) - max(x0, ax0)) * max(0.0, min(y1, ay1) - max(y0, ay0))
                   / ((x1 - x0) * (y1 - y0)))
        s = unc.sigma_px[(ry == by) & (rx == bx)]
        s = s[np.isfinite(s)]
        if covered < 0.5 or len(s) == 0:
            outside.append(f"capture frames with the target {where} of the image: most of it lies "
                           "outside the calibrated area")
        elif np.percentile(s, 90) > threshold_px:
            high.append((float(s.max()), where))
    if len(high) == len(_REGIONS):
        worst = max(v for v, _ in high)
        return [f"capture more frames over the whole image (uncertainty {unc.median():.2g} px median, "
                f"up to {worst:.2g} px)"]
    high.sort(reverse=True)
    return outside + [f"capture more frames with the target {where} of the image (uncertainty up to "
                      f"{v:.2g} px there)" for v, where in high]


def draw_lattice_map(ax: Axes, x: np.ndarray, y: np.ndarray, shape: tuple[int, int], values: np.ndarray,
                     width: int, height: int, title: str, **imshow: Any) -> AxesImage:
    """``values (K,)`` on the pixel lattice ``x, y (K,)`` (``shape (ny, nx)``, OpenCV px) over the
    whole ``width x height`` image, grey outside the lattice; returns the image for a colour bar."""
    ny, nx = shape
    xs, ys = x.reshape(shape)[0], y.reshape(shape)[:, 0]
    hx, hy = (xs[-1] - xs[0]) / max(nx - 1, 1) / 2, (ys[-1] - ys[0]) / max(ny - 1, 1) / 2
    im = ax.imshow(values.reshape(shape), interpolation="nearest",
                   extent=(xs[0] - hx, xs[-1] + hx, ys[-1] + hy, ys[0] - hy), **imshow)
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(height - 0.5, -0.5)
    ax.set_facecolor("0.75")
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    return im


def uncertainty_figure(maps: Sequence[tuple[str, ProjectionUncertainty]], width: int, height: int) -> Figure:
    """Colour maps of ``sigma_px`` side by side (one per ``(title, map)``), one logarithmic px
    scale; each panel the whole image, its title with the map's median."""
    if not maps:
        raise ValueError("no uncertainty map to draw")
    values = np.concatenate([u.sigma_px[np.isfinite(u.sigma_px) & (u.sigma_px > 0)] for _, u in maps])
    lo, hi = (np.percentile(values, [1, 99]) if len(values) else (1e-3, 1.0))
    norm = colors.LogNorm(max(float(lo), 1e-5), max(float(hi), 2 * max(float(lo), 1e-5)))
    fig = Figure(figsize=(5.2 * len(maps) + 1.3, 5.2 * height / width + 1.0), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(maps), squeeze=False)[0]
    im = None
    for ax, (title, unc) in zip(axes, maps, strict=True):
        im = draw_lattice_map(ax, unc.x, unc.y, unc.shape, unc.sigma_px, width, height,
                              f"{title}: median {unc.median():.3g} px", cmap="viridis", norm=norm)
    assert im is not None  # maps is not empty
    fig.colorbar(im, ax=list(axes), label="1-sigma projection uncertainty (px, log scale)", extend="both",
                 fraction=0.03, pad=0.02)
    return fig


def cross_validation_figure(diff: CrossValidationDiff, width: int, height: int) -> Figure:
    """The cross-validation diff over the whole image, a px colour scale."""
    fig = Figure(figsize=(6.5, 6.5 * height / width + 1.0), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    im = draw_lattice_map(ax, diff.x, diff.y, diff.shape, diff.diff_px, width, height,
                          f"generic cameras of two halves of the frames: median {diff.median_px:.3g} px",
                          cmap="magma")
    fig.colorbar(im, ax=ax, label="difference after the best-fit rotation (px)", fraction=0.03, pad=0.02)
    return fig


def save_figure_png(path: str | os.PathLike[str], fig: Figure) -> Path:
    """Write ``fig`` as a PNG (100 dpi) atomically; returns the path."""
    out = Path(path)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=100)
    return out


def save_uncertainty_png(path: str | os.PathLike[str], maps: Sequence[tuple[str, ProjectionUncertainty]],
                         width: int, height: int) -> Path:
    """:func:`uncertainty_figure` written atomically to ``path``."""
    return save_figure_png(path, uncertainty_figure(maps, width, height))


def save_uncertainty_npz(path: str | os.PathLike[str], unc: ProjectionUncertainty,
                         sharp: ProjectionUncertainty | None = None) -> Path:
    """Write ``x, y, sigma_px, noise_px`` (and ``sigma_px_sharp, noise_px_sharp``) to ``path``.

    ``x, y, sigma_px`` are ``(ny, nx)`` arrays on ``unc``'s lattice (px, OpenCV convention);
    ``sigma_px_sharp`` is ``sharp``'s map interpolated onto that lattice (NaN outside its
    calibrated area). Written atomically; returns ``path``.
    """
    arrays = {"x": unc.x.reshape(unc.shape), "y": unc.y.reshape(unc.shape),
              "sigma_px": unc.sigma_px.reshape(unc.shape), "noise_px": np.float64(unc.noise_px)}
    if sharp is not None:
        arrays["sigma_px_sharp"] = sharp.at(np.column_stack([unc.x, unc.y])).reshape(unc.shape)
        arrays["noise_px_sharp"] = np.float64(sharp.noise_px)
    out = Path(path)
    with atomic_path(out) as tmp, open(tmp, "wb") as handle:
        np.savez_compressed(handle, **arrays)  # type: ignore[arg-type]  # numpy stubs: **arrays vs allow_pickle
    return out
