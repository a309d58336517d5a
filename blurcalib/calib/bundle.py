"""Bundle adjustment of the central generic camera (:mod:`blurcalib.camera.generic`) over many frames.

Problem. Observation ``i`` of frame ``f`` sees target point ``P_i`` (m, fixed: the parametric
calibration's refined points) at ``p_i`` px (OpenCV convention). With the pose
``M_f = [R_f | t_f]``, the generic projection ``pi_G`` and, for blurry frames, a per-frame image
translation ``s_f`` (the deconvolution's translational ambiguity, paper ``eq:global_align``)::

    r_i = p_i - pi_G(R_f P_i + t_f) - s_f

    min  sum_i w_i rho(|r_i|^2) + |s_f|^2 / sigma_s^2 + sum |D2 v - D2 v0|^2 / sigma_D^2

* ``rho``: Huber on the 2-D residual norm at ``huber_px`` (1 px, as the reference tool), solved
  by iteratively reweighted Gauss-Newton; ``w_i`` per-observation weights.
* ``sigma_s`` (``shift_sigma_px``): the shift's weak prior (frames whose shift is free only).
* ``D2``: second differences of the node directions along grid rows and columns; ``v0`` the
  initial grid. A weak smoothness prior (``smoothness_px``, converted to radians by the grid's
  angular pitch) that only matters where no observation pins a node: there the grid follows the
  initial (parametric) camera's shape instead of drifting. Cells without observations are
  reported in :attr:`BundleResult.warnings` by image region.

Solver: Levenberg-Marquardt (Marquardt's ``lambda diag(H)`` damping, starting at 1e-6, divided by 5 on
success, x4 on failure; a step that raises the cost by less than ``tol`` of it ends the
iterations as converged: the projections are solved to 1e-8 px, which makes a converged cost
that uncertain). The per-frame blocks (pose: rotation increment ``omega`` with
``R <- exp(omega) R`` and ``t <- t + dt``; plus ``s_f``) are eliminated by the Schur complement;
the reduced system on the ``2 GW GH`` grid parameters is dense (formed frame chunk by frame
chunk, :func:`reduce_frames`) and solved to float64 accuracy (on a CPU by a float32 Cholesky
factor refined in float64: :func:`blurcalib.calib.spd_solve.solve_lower`). Projections are
warm-started from the previous iteration's pixels; an observation whose ray leaves the
calibrated area gets weight 0 (a clamped projection carries no gradient).

Gauge. A central model's orientation is free (rotating every direction and every pose together
changes nothing). As the reference tool does, after every accepted step the grid is re-rotated
so that the image centre looks along +z and the centre of the right edge lies in the x-z plane
(x > 0), and the poses are rotated with it.

Rolling shutter (optional, :class:`RollingRows`). A moving frame read row by row is seen from
its pose moved by the motion over its row's instant (``docs/rolling-shutter.md``); with
``y_i`` the observation's row as a share of the readout, its camera point becomes::

    X_i = exp([y_i a_w + y_i^2 b_w]_x) (R_f P_i + t_f) + y_i a_v + y_i^2 b_v

with the frame's rolling parameters ``theta_f = (a_w rad, a_v m, b_w rad, b_v m)`` (12 values,
zero-mean Gaussian prior of ``twist_sigma`` rad and ``twist_sigma`` times the frame's distance
m). The per-frame blocks then hold ``omega, dt, s, theta`` (20 columns) and are eliminated by
the same Schur complement; without rolling rows they hold 8 columns and nothing changes.

Outliers: once, after ``outlier_iteration`` iterations (or at convergence if that comes first),
observations with an error above ``Q3 + 6 (Q3 - Q1)`` (quartiles of the error norms) are removed,
as the reference tool does.

The result keeps its observations (:class:`BundleData`), from which
:mod:`blurcalib.calib.normal_equations` rebuilds the Gauss-Newton blocks at the solution (the
projection uncertainty's information, the held-out validation's leave-out cameras).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from numpy.typing import ArrayLike

from blurcalib.calib.coverage import cell_coverage, coverage_warnings
from blurcalib.calib.frame_block import (
    RollingRows,
    checked_rolling_rows,
    frame_jacobian,
    rolling_frame_jacobian,
    rolling_points,
    rolling_prior_weights,
)
from blurcalib.calib.spd_solve import solve_lower
from blurcalib.camera.generic import (
    CentralGeneric,
    GridSpline,
    accumulate_blocks,
    apply_update,
    param_columns,
    projection_jacobians,
    tangent_basis,
)
from blurcalib.geometry.lie import exp_so3, orthonormal
from blurcalib.geometry.pose import Pose

__all__ = [
    "BundleData",
    "BundleProblem",
    "BundleResult",
    "BundleSettings",
    "BundleState",
    "add_priors",
    "add_shift_prior",
    "add_smoothness_prior",
    "bundle_adjust",
    "data_equations",
    "gauge_rotation",
    "reduce_frames",
    "robust_weights",
]

log = logging.getLogger(__name__)

OBSERVATION_CHUNK = 16384
"""Observations whose Jacobian products are formed at once when the normal equations are
accumulated (memory per chunk about 16 kB per observation)."""

FRAME_CHUNK = 64
"""Frames whose Schur complement terms are formed by one matrix product (:func:`reduce_frames`)."""

ROW_BLOCK = 512
"""Rows of the reduced system per product when :func:`reduce_frames` forms its lower triangle
alone, block row by block row."""


@dataclass(frozen=True)
class BundleSettings:
    """Options of :func:`bundle_adjust`.

    Attributes:
        huber_px: Huber threshold on the residual norm (px).
        max_iterations: LM iterations at most.
        tol: stop when an accepted step lowers the cost by less than this fraction.
        outlier_iteration: iteration after which outliers are removed once (0: never).
        outlier_iqr: the rule's factor ``k`` in ``Q3 + k (Q3 - Q1)``.
        shift_sigma_px: prior standard deviation of a free per-frame shift (px).
        smoothness_px: prior standard deviation of the grid's second differences from the
            initial grid's, in px (via the grid's angular pitch).
        device: torch device.
    """

    huber_px: float = 1.0
    max_iterations: int = 40
    tol: float = 1e-7
    outlier_iteration: int = 3
    outlier_iqr: float = 6.0
    shift_sigma_px: float = 20.0
    smoothness_px: float = 1.0
    device: str = "cpu"


@dataclass(eq=False)
class BundleData:
    """The observations of a bundle adjustment, as its final iteration used them.

    Attributes:
        frame: ``(N,)`` frame index of each observation.
        points: ``(N, 3)`` target points (m).
        observed: ``(N, 2)`` observed positions (px, OpenCV convention).
        weights: ``(N,)`` observation weights, 0 for the removed outliers.
        shift_free: ``(F,)`` bool, frames with a free image shift.
        settings: the solver options (priors, Huber threshold, device).
        angular_pitch: radians per pixel of the grid, as the smoothness prior converted
            ``smoothness_px`` with it.
    """

    frame: np.ndarray = field(repr=False)
    points: np.ndarray = field(repr=False)
    observed: np.ndarray = field(repr=False)
    weights: np.ndarray = field(repr=False)
    shift_free: np.ndarray
    settings: BundleSettings
    angular_pitch: float


@dataclass(eq=False)
class BundleResult:
    """The adjusted generic camera, poses and per-frame shifts.

    Attributes:
        model: the generic camera (gauge: image centre along +z, right edge in the x-z plane).
        poses: ``(F,)`` poses (target -> camera) in the model's frame.
        shifts: ``(F, 2)`` px per-frame image shifts ``s_f`` (0 where not free).
        residuals: ``(N, 2)`` px ``p_i - pi_G(M_f P_i) - s_f``; NaN where the ray left the area.
        inlier: ``(N,)`` bool, used in the final fit (not an outlier, inside the area, w > 0).
        median_error, rms_error: over inliers (px).
        iterations: LM iterations run; cost: final objective.
        seconds, cpu_seconds: wall-clock and process CPU time.
        warnings: one line per image region with unobserved grid cells.
        coverage: ``(GH - 3, GW - 3)`` observation count per grid cell of the calibrated area.
        data: the observations and options (what
            :func:`blurcalib.calib.normal_equations.normal_equations` needs).
        theta: ``(F, 12)`` rolling parameters (0 for frames without), or None without rolling rows.
    """

    model: CentralGeneric
    poses: list[Pose]
    shifts: np.ndarray
    residuals: np.ndarray = field(repr=False)
    inlier: np.ndarray = field(repr=False)
    median_error: float
    rms_error: float
    iterations: int
    cost: float
    seconds: float
    cpu_seconds: float
    warnings: list[str]
    coverage: np.ndarray = field(repr=False)
    data: BundleData = field(repr=False)
    theta: np.ndarray | None = field(default=None, repr=False)


@dataclass
class BundleState:
    """The unknowns of one bundle adjustment at an iterate, with the projections that warm-start the next."""

    grid: torch.Tensor  # (GH, GW, 3)
    grid0: torch.Tensor  # (GH, GW, 3) initial grid, rotated with the gauge
    R: torch.Tensor  # (F, 3, 3)
    t: torch.Tensor  # (F, 3)
    s: torch.Tensor  # (F, 2)
    u: torch.Tensor  # (N, 2) current projections (warm starts)
    inside: torch.Tensor  # (N,) bool
    theta: torch.Tensor | None = None  # (F, 12) rolling parameters


class BundleProblem:
    """Fixed data and the objective of one bundle adjustment."""

    def __init__(self, spline: GridSpline, frame: torch.Tensor, points: torch.Tensor,
                 observed: torch.Tensor, weights: torch.Tensor, shift_free: torch.Tensor,
                 settings: BundleSettings, rolling: RollingRows | None = None) -> None:
        self.spline = spline
        self.frame = frame
        self.points = points
        self.observed = observed
        self.weights = weights
        self.shift_free = shift_free
        self.settings = settings
        gh, gw = spline.shape
        self.gh, self.gw = gh, gw
        self.num_frames = len(shift_free)
        self.pitch = _angular_pitch(spline)
        self.smooth_w = 1.0 / (settings.smoothness_px * self.pitch) ** 2
        self.shift_w = 1.0 / settings.shift_sigma_px ** 2
        self.triples = _second_difference_triples(gh, gw, spline.grid.device)
        self.block = 8 if rolling is None else 20
        self.row: torch.Tensor | None = None
        self.moving: torch.Tensor | None = None
        self.theta_w: torch.Tensor | None = None
        if rolling is not None:
            self.row = torch.as_tensor(rolling.row, dtype=points.dtype, device=points.device)
            self.moving = torch.as_tensor(rolling.moving, device=points.device)
            self.twist_sigma = rolling.twist_sigma

    def set_distance(self, t: torch.Tensor) -> None:
        """The rolling parameters' prior weights ``(F, 12)`` from the frames' distances ``|t_f|``
        (:func:`blurcalib.calib.frame_block.rolling_prior_weights`)."""
        self.theta_w = rolling_prior_weights(t, self.twist_sigma)

    def rolling_camera_points(self, R: torch.Tensor, t: torch.Tensor, theta: torch.Tensor | None,
                              sel: torch.Tensor | None = None
                              ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """``X (N, 3)``, the rolling rotations (None without rolling rows) and ``R P`` of the
        observations ``sel`` (default all)."""
        fr = self.frame if sel is None else self.frame[sel]
        P = self.points if sel is None else self.points[sel]
        if self.row is None or theta is None:
            RP = torch.einsum("nij,nj->ni", R[fr], P)
            return RP + t[fr], None, RP
        y = self.row if sel is None else self.row[sel]
        return rolling_points(R, t, theta, fr, P, y)

    def project(self, grid: torch.Tensor, R: torch.Tensor, t: torch.Tensor,
                s: torch.Tensor, init: torch.Tensor, theta: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Projections ``(N, 2)``, inside ``(N,)`` and residuals ``(N, 2)`` for trial values."""
        X = self.rolling_camera_points(R, t, theta)[0]
        u, inside = self.spline.with_grid(grid).project(X, init)
        inside = inside & (X[:, 2] > 0)
        r = self.observed - u - s[self.frame]
        return u, inside, r

    def data_cost(self, r: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """``sum w rho(|r|^2)`` with Huber's ``rho`` (``e^2`` inside, ``2 d e - d^2`` beyond)."""
        d = self.settings.huber_px
        e = r.norm(dim=-1)
        rho = torch.where(e <= d, e * e, 2 * d * e - d * d)
        return (w * rho).sum()

    def prior_cost(self, grid: torch.Tensor, grid0: torch.Tensor, s: torch.Tensor,
                   theta: torch.Tensor | None = None) -> torch.Tensor:
        """Smoothness prior on the grid's second differences plus the free shifts' prior and,
        with rolling rows, the moving frames' rolling parameters' prior (px^2)."""
        i, j, k = self.triples
        g, g0 = grid.reshape(-1, 3), grid0.reshape(-1, 3)
        d2 = (g[i] - 2 * g[j] + g[k]) - (g0[i] - 2 * g0[j] + g0[k])
        free = self.shift_free.to(s.dtype)[:, None]
        cost = self.smooth_w * (d2 * d2).sum() + self.shift_w * (free * s * s).sum()
        if theta is not None and self.theta_w is not None and self.moving is not None:
            cost = cost + (self.moving.to(s.dtype)[:, None] * self.theta_w * theta * theta).sum()
        return cost

    def cost(self, st: BundleState, r: torch.Tensor, w: torch.Tensor) -> float:
        """The objective: data cost plus priors (px^2)."""
        return float(self.data_cost(r, w) + self.prior_cost(st.grid, st.grid0, st.s, st.theta))


def _angular_pitch(spline: GridSpline) -> float:
    """Radians per pixel of the grid: the median angle between neighbouring nodes / cell length."""
    g = spline.grid
    ang = torch.acos(torch.clamp((g[:, 1:] * g[:, :-1]).sum(-1), -1.0, 1.0))
    return float(torch.median(ang)) * float(spline.scale[0])


def _second_difference_triples(gh: int, gw: int, device: torch.device
                               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Flat node indices ``(i, j, k)`` of every three consecutive nodes along rows and columns."""
    idx = torch.arange(gh * gw, device=device).reshape(gh, gw)
    rows = (idx[:, :-2].reshape(-1), idx[:, 1:-1].reshape(-1), idx[:, 2:].reshape(-1))
    cols = (idx[:-2].reshape(-1), idx[1:-1].reshape(-1), idx[2:].reshape(-1))
    return tuple(torch.cat([a, b]) for a, b in zip(rows, cols, strict=True))


def robust_weights(r: torch.Tensor, huber_px: float) -> torch.Tensor:
    """IRLS weights of Huber's loss on the residual norm: 1 inside, ``delta / e`` beyond."""
    e = r.norm(dim=-1)
    return torch.where(e <= huber_px, torch.ones_like(e), huber_px / e.clamp_min(1e-300))


def _normal_equations(pb: BundleProblem, st: BundleState, w: torch.Tensor, r: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor,
                                 torch.Tensor]:
    """Gauss-Newton blocks: ``Hgg (G, G)``, ``Hgp (G, F, K)``, ``Hpp (F, K, K)``, ``bg``, ``bp``.

    Per-frame block columns: ``omega (3), dt (3), s (2)`` and, with rolling rows, ``theta (12)``
    (``K = pb.block``). Also returns the grid's node tangents.
    """
    Hgg, Hgp, Hpp, bg, bp, tang = data_equations(pb, st, w, r)
    add_priors(pb, st, tang, Hgg, bg, Hpp, bp)
    return Hgg, Hgp, Hpp, bg, bp, tang


def data_equations(pb: BundleProblem, st: BundleState, w: torch.Tensor, r: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor,
                               torch.Tensor]:
    """The observations' part of :func:`_normal_equations` (no priors).

    Accumulated :data:`OBSERVATION_CHUNK` observations at a time, so that the per-observation
    products (``(n, 32, 32)``) stay small whatever the number of observations.
    """
    G = 2 * pb.gh * pb.gw
    F = pb.num_frames
    K = pb.block
    dt, dev = pb.points.dtype, pb.points.device
    n_nodes = pb.gh * pb.gw
    spline = pb.spline.with_grid(st.grid)
    Hcell = torch.zeros(n_nodes, 32, 32, dtype=dt, device=dev)
    Hgp = torch.zeros(G * F * K, dtype=dt, device=dev)
    Hpp = torch.zeros(F, K, K, dtype=dt, device=dev)
    bp = torch.zeros(F, K, dtype=dt, device=dev)
    bg = torch.zeros(G, dtype=dt, device=dev)
    lanes = torch.arange(K, device=dev)
    for sel in torch.nonzero(w > 0).squeeze(1).split(OBSERVATION_CHUNK):
        fr = pb.frame[sel]
        X, Ri, RP = pb.rolling_camera_points(st.R, st.t, st.theta, sel)
        J_p, J_g, nodes = projection_jacobians(spline, st.u[sel], X)
        if Ri is None or pb.row is None:
            J_pose = frame_jacobian(J_p, X - st.t[fr])
        else:
            J_pose = rolling_frame_jacobian(J_p, Ri, RP, X, pb.row[sel])
        wJg = w[sel][:, None, None] * J_g
        rs = r[sel][:, :, None]
        Hcell.index_add_(0, nodes[:, 0], wJg.transpose(1, 2) @ J_g)
        cols = param_columns(nodes)
        flat = cols[:, :, None] * (F * K) + fr[:, None, None] * K + lanes
        Hgp.index_add_(0, flat.reshape(-1), (wJg.transpose(1, 2) @ J_pose).reshape(-1))
        wJp = w[sel][:, None, None] * J_pose
        Hpp.index_add_(0, fr, wJp.transpose(1, 2) @ J_pose)
        bp.index_add_(0, fr, (wJp.transpose(1, 2) @ rs)[..., 0])
        bg.index_add_(0, cols.reshape(-1), (wJg.transpose(1, 2) @ rs).reshape(-1))
    used = torch.nonzero(Hcell.abs().sum((1, 2)) > 0).squeeze(1)
    Hgg = torch.zeros(G, G, dtype=dt, device=dev)
    accumulate_blocks(Hgg, param_columns(_cell_nodes(used, pb.gw)), Hcell[used])
    Hgp = Hgp.reshape(G, F, K)
    Hgp[:, ~pb.shift_free, 6:8] = 0.0
    if pb.moving is not None:
        Hgp[:, ~pb.moving, 8:] = 0.0
    tang = tangent_basis(st.grid.reshape(-1, 3))
    return Hgg, Hgp, Hpp, bg, bp, tang


def _cell_nodes(first: torch.Tensor, gw: int) -> torch.Tensor:
    """The 16 flat node indices of the cells whose first (top-left) node is ``first (K,)``."""
    offs = torch.arange(4, device=first.device)
    return (first[:, None, None] + offs[:, None] * gw + offs[None, :]).reshape(len(first), 16)


def add_priors(pb: BundleProblem, st: BundleState, tang: torch.Tensor, Hgg: torch.Tensor, bg: torch.Tensor,
                Hpp: torch.Tensor, bp: torch.Tensor) -> None:
    """Add the smoothness prior (grid), the shift prior and, with rolling rows, the rolling
    parameters' prior (frames) to the normal equations."""
    add_smoothness_prior(pb, st, tang, Hgg, bg)
    add_shift_prior(pb, st, Hpp, bp)
    add_rolling_prior(pb, st, Hpp, bp)


def add_smoothness_prior(pb: BundleProblem, st: BundleState, tang: torch.Tensor, Hgg: torch.Tensor | None,
                          bg: torch.Tensor) -> None:
    """Add the smoothness prior's Hessian (unless ``Hgg`` is None) and gradient side."""
    i, j, k = pb.triples
    g, g0 = st.grid.reshape(-1, 3), st.grid0.reshape(-1, 3)
    res = (g[i] - 2 * g[j] + g[k]) - (g0[i] - 2 * g0[j] + g0[k])
    J = torch.stack([tang[i], -2 * tang[j], tang[k]], 1)  # (T, 3 nodes, 2, 3)
    Jm = J.permute(0, 3, 1, 2).reshape(len(i), 3, 6)
    nodes = torch.stack([i, j, k], 1)
    cols = param_columns(nodes)
    if Hgg is not None:
        accumulate_blocks(Hgg, cols, pb.smooth_w * Jm.transpose(1, 2) @ Jm)
    bg.index_add_(0, cols.reshape(-1), -pb.smooth_w * (Jm.transpose(1, 2) @ res[:, :, None]).reshape(-1))


def add_shift_prior(pb: BundleProblem, st: BundleState, Hpp: torch.Tensor, bp: torch.Tensor) -> None:
    """Add the free shifts' prior; decouple the fixed shifts (identity block, zero gradient)."""
    free = pb.shift_free
    Hpp[free, 6, 6] += pb.shift_w
    Hpp[free, 7, 7] += pb.shift_w
    bp[free, 6:8] -= pb.shift_w * st.s[free]
    fixed = ~pb.shift_free
    Hpp[fixed, 6:8, :] = 0.0
    Hpp[fixed, :, 6:8] = 0.0
    Hpp[fixed, 6, 6] = 1.0
    Hpp[fixed, 7, 7] = 1.0
    bp[fixed, 6:8] = 0.0


def add_rolling_prior(pb: BundleProblem, st: BundleState, Hpp: torch.Tensor, bp: torch.Tensor) -> None:
    """With rolling rows: add the moving frames' rolling parameters' prior and decouple the other
    frames' (identity block, zero gradient); without, nothing."""
    if pb.moving is None or pb.theta_w is None or st.theta is None:
        return
    m, still = pb.moving, ~pb.moving
    Hpp[m, 8:, 8:] += torch.diag_embed(pb.theta_w[m])
    bp[m, 8:] -= pb.theta_w[m] * st.theta[m]
    Hpp[still, 8:, :] = 0.0
    Hpp[still, :, 8:] = 0.0
    Hpp[still, 8:, 8:] = torch.eye(12, dtype=Hpp.dtype, device=Hpp.device)
    bp[still, 8:] = 0.0


def reduce_frames(Hgg: torch.Tensor, Hgp: torch.Tensor, Hpp_inv: torch.Tensor, bg: torch.Tensor | None = None,
                  bp: torch.Tensor | None = None, lower: bool = False, overwrite: bool = False
                  ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The reduced camera system: the per-frame blocks eliminated by the Schur complement::

        S = Hgg - sum_f Hgp_f Hpp_f^-1 Hgp_f^T        (G, G)
        c = bg  - sum_f Hgp_f Hpp_f^-1 bp_f            (G,)

    from ``Hgg (G, G)``, ``Hgp (G, F, 8)``, ``Hpp_inv (F, 8, 8)`` and, optionally, ``bg (G,)``,
    ``bp (F, 8)`` (``c`` is None without them). With ``lower``, only the lower triangle of ``S``
    is formed (its upper triangle keeps ``Hgg``'s): all a Cholesky factorisation reads, at about
    half the products. A frame's rows of ``Hgp`` are zero outside the grid parameters its
    observations touch, which lie within one span of rows (the target's footprint); frames are
    sorted by that span and taken :data:`FRAME_CHUNK` at a time, each chunk's product restricted
    to the union of its spans. Memory: ``S`` and one chunk; with ``overwrite``, ``S`` is formed in
    ``Hgg``'s storage (``Hgg`` is lost).
    """
    G = Hgp.shape[0]
    S = Hgg if overwrite else Hgg.clone()
    c = None if bg is None else bg.clone()
    touched = (Hgp != 0).any(2)
    rows = torch.arange(G, device=Hgp.device)[:, None]
    first = torch.where(touched, rows, G).amin(0)
    last = torch.where(touched, rows, -1).amax(0)
    order = torch.argsort(first)
    order = order[first[order] < G]
    for chunk in order.split(FRAME_CHUNK):
        a, b = int(first[chunk].min()), int(last[chunk].max()) + 1
        H = Hgp[a:b, chunk]
        Y = torch.einsum("gfi,fij->gfj", H, Hpp_inv[chunk]).reshape(b - a, -1)
        H = H.reshape(b - a, -1)
        if lower:
            for i in range(a, b, ROW_BLOCK):
                j = min(i + ROW_BLOCK, b)
                S[i:j, a:j].addmm_(Y[i - a:j - a], H[:j - a].T, alpha=-1.0)
        else:
            S[a:b, a:b].addmm_(Y, H.T, alpha=-1.0)
        if c is not None and bp is not None:
            c[a:b].sub_(Y @ bp[chunk].reshape(-1))
    return S, c


def _solve(Hgg: torch.Tensor, Hgp: torch.Tensor, Hpp: torch.Tensor, bg: torch.Tensor,
           bp: torch.Tensor, lam: float) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Damped step ``(dg (G,), dp (F, K))`` by the Schur complement; None if not positive definite."""
    eye = torch.eye(Hpp.shape[1], dtype=Hpp.dtype, device=Hpp.device)
    Hpp_d = Hpp + lam * torch.diag_embed(torch.diagonal(Hpp, dim1=1, dim2=2)) + 1e-12 * eye
    try:
        Lp = torch.linalg.cholesky(Hpp_d)
    except torch.linalg.LinAlgError:
        return None
    Hpp_inv = torch.cholesky_inverse(Lp)
    S, rhs = reduce_frames(Hgg, Hgp, Hpp_inv, bg, bp, lower=True)
    diag = torch.diagonal(Hgg)
    S.diagonal().add_(lam * diag + 1e-12 * float(diag.mean()))
    try:
        dg = solve_lower(S, rhs)
    except torch.linalg.LinAlgError:
        return None
    dp = torch.einsum("fij,fj->fi", Hpp_inv, bp - torch.einsum("gfi,g->fi", Hgp, dg))
    return dg, dp


def gauge_rotation(spline: GridSpline, grid: torch.Tensor) -> torch.Tensor:
    """``Q (3, 3)``: maps the image centre's direction to +z and the right edge's into x-z (x > 0)."""
    lo, hi = spline.lo, spline.hi
    mid = 0.5 * (lo + hi)
    px = torch.stack([mid, torch.stack([hi[0], mid[1]])])
    d = spline.with_grid(grid).evaluate(px).d
    z = d[0]
    x = d[1] - (d[1] @ z) * z
    x = x / x.norm()
    y = torch.linalg.cross(z, x, dim=0)
    return torch.stack([x, y, z])


def _checked_inputs(F: int, frame: ArrayLike, points: ArrayLike, observed: ArrayLike,
                    weights: ArrayLike | None, shift_free: ArrayLike | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`bundle_adjust`'s observations as arrays ``frame (N,)``, ``points (N, 3)``,
    ``observed (N, 2)``, ``weights (N,)`` and ``shift_free (F,)``; ValueError names what is wrong."""
    fr_np = np.asarray(frame, dtype=np.int64).reshape(-1)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(observed, dtype=np.float64).reshape(-1, 2)
    n = len(fr_np)
    if P.shape[0] != n or p.shape[0] != n:
        raise ValueError(f"need frame (N,), points (N, 3), observed (N, 2); got {n}, {P.shape}, {p.shape}")
    if n == 0 or fr_np.min() < 0 or fr_np.max() >= F:
        raise ValueError(f"frame indices must lie in [0, {F})")
    counts = np.bincount(fr_np, minlength=F)
    if np.any(counts == 0):
        raise ValueError(f"frames without observations: {np.nonzero(counts == 0)[0].tolist()[:10]}")
    w_np = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if w_np.shape != (n,) or np.any(w_np < 0) or not np.all(np.isfinite(w_np)):
        raise ValueError(f"weights must be finite, >= 0 and of shape ({n},)")
    free_np = np.zeros(F, bool) if shift_free is None else np.asarray(shift_free, bool).reshape(-1)
    if free_np.shape != (F,):
        raise ValueError(f"shift_free must have shape ({F},)")
    return fr_np, P, p, w_np, free_np


def _remove_outliers(pb: BundleProblem, st: BundleState, r: torch.Tensor, use: torch.Tensor
                     ) -> tuple[torch.Tensor, float]:
    """Give the observations with an error above ``Q3 + k (Q3 - Q1)`` (over those in use) weight 0
    in ``pb``; the new use weights ``(N,)`` and cost."""
    e = r.norm(dim=-1)[use > 0]
    q1, q3 = torch.quantile(e, 0.25), torch.quantile(e, 0.75)
    thresh = float(q3 + pb.settings.outlier_iqr * (q3 - q1))
    outlier = r.norm(dim=-1) > thresh
    pb.weights = torch.where(outlier, 0.0, pb.weights)
    use = pb.weights * st.inside.to(torch.float64)
    log.info("outlier removal: %d observations above %.3f px", int(outlier.sum()), thresh)
    return use, pb.cost(st, torch.where(st.inside[:, None], r, 0.0), use)


def _regauged(spline: GridSpline, st: BundleState) -> BundleState:
    """``st`` rotated into the gauge (module docstring): grid, initial grid, poses and rolling
    parameters by the rotation :func:`gauge_rotation` gives for its grid."""
    Q = gauge_rotation(spline, st.grid)
    theta = None if st.theta is None else (st.theta.reshape(-1, 4, 3) @ Q.T).reshape(-1, 12)
    return BundleState(st.grid @ Q.T, st.grid0 @ Q.T, Q @ st.R, st.t @ Q.T, st.s, st.u, st.inside, theta)


def bundle_adjust(model: CentralGeneric, poses: Sequence[Pose], frame: ArrayLike, points: ArrayLike,
                  observed: ArrayLike, weights: ArrayLike | None = None,
                  shift_free: ArrayLike | None = None, settings: BundleSettings | None = None,
                  progress: bool = False, prior: CentralGeneric | None = None,
                  rolling: RollingRows | None = None) -> BundleResult:
    """Fit the generic camera's grid, every frame's pose and the free per-frame shifts.

    Args:
        model: initial generic camera (e.g. :func:`blurcalib.camera.generic.fit_to_rays` of the
            parametric calibration); its calibrated area and grid size are kept.
        poses: ``(F,)`` initial poses (target -> camera) in ``model``'s camera frame.
        frame: ``(N,)`` frame index of each observation.
        points: ``(N, 3)`` target points (m).
        observed: ``(N, 2)`` observed positions (px, OpenCV convention).
        weights: ``(N,)`` observation weights ``>= 0`` (default 1).
        shift_free: ``(F,)`` bool, frames with a free image shift ``s_f`` (blurry frames).
        settings: solver options.
        progress: log one line per iteration.
        prior: the camera whose shape the smoothness prior keeps (its grid's second
            differences; same grid as ``model``, each in its own gauge). Default ``model``: a
            warm start from another fit's camera passes the initial camera of a cold start here,
            so that cells without observations follow it and not the warm start.
        rolling: the rows and the moving frames of the rolling-shutter geometry (module
            docstring); None: the global shutter.

    Raises:
        ValueError: inconsistent shapes or a frame without observations.
    """
    settings = settings or BundleSettings()
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    dev = torch.device(settings.device)
    kw = {"dtype": torch.float64, "device": dev}
    fr_np, P, p, w_np, free_np = _checked_inputs(len(poses), frame, points, observed, weights, shift_free)
    F = len(poses)

    spline = model.spline(dev)
    pb = BundleProblem(spline, torch.as_tensor(fr_np, device=dev), torch.as_tensor(P, **kw),
                       torch.as_tensor(p, **kw), torch.as_tensor(w_np, **kw),
                       torch.as_tensor(free_np, device=dev), settings,
                       checked_rolling_rows(rolling, len(P), F))
    Q = gauge_rotation(spline, spline.grid)
    grid = spline.grid @ Q.T
    grid0 = grid.clone()
    if prior is not None:
        if (prior.grid_height, prior.grid_width) != spline.shape:
            raise ValueError(f"prior grid {prior.grid_height}x{prior.grid_width} differs from the model's "
                             f"{spline.shape[0]}x{spline.shape[1]}")
        prior_grid = prior.spline(dev).grid
        grid0 = prior_grid @ gauge_rotation(spline, prior_grid).T
    R = Q @ torch.as_tensor(np.stack([q.R for q in poses]), **kw)
    t = torch.as_tensor(np.stack([q.t for q in poses]), **kw) @ Q.T
    s = torch.zeros(F, 2, **kw)
    theta = None
    if rolling is not None:
        theta = torch.zeros(F, 12, **kw)
        pb.set_distance(t)
    u, inside, r = pb.project(grid, R, t, s, None, theta)
    st = BundleState(grid, grid0, R, t, s, u, inside, theta)
    use = pb.weights * inside.to(torch.float64)
    cost = pb.cost(st, torch.where(inside[:, None], r, 0.0), use)
    lam = 1e-6
    it = 0
    removed = not settings.outlier_iteration
    remove_after = settings.outlier_iteration
    for it in range(1, settings.max_iterations + 1):
        if not removed and it > remove_after:
            removed = True
            use, cost = _remove_outliers(pb, st, r, use)
        w = use * robust_weights(r, settings.huber_px)
        Hgg, Hgp, Hpp, bg, bp, _tang = _normal_equations(pb, st, w, r)
        accepted = False
        while lam < 1e8:
            step = _solve(Hgg, Hgp, Hpp, bg, bp, lam)
            if step is None:
                lam *= 4
                continue
            dg, dp = step
            grid_n = apply_update(st.grid, dg.reshape(pb.gh, pb.gw, 2))
            R_n = exp_so3(dp[:, :3]) @ st.R
            t_n = st.t + dp[:, 3:6]
            s_n = st.s + dp[:, 6:8]
            theta_n = None if st.theta is None else st.theta + dp[:, 8:]
            u_n, in_n, r_n = pb.project(grid_n, R_n, t_n, s_n, st.u, theta_n)
            use_n = pb.weights * in_n.to(torch.float64)
            trial = BundleState(grid_n, st.grid0, R_n, t_n, s_n, u_n, in_n, theta_n)
            cost_n = pb.cost(trial, torch.where(in_n[:, None], r_n, 0.0), use_n)
            if cost_n < cost:
                rel = (cost - cost_n) / max(cost, 1e-300)
                st, r, use, cost = _regauged(spline, trial), r_n, use_n, cost_n
                lam = max(lam * 0.2, 1e-12)
                accepted = True
                break
            if cost_n - cost <= settings.tol * cost:  # within the projections' noise: converged
                break
            lam *= 4
        if progress:
            log.info("iteration %d: cost %.6g, lambda %.2g", it, cost, lam)
        if not accepted or rel < settings.tol:
            if removed:
                break
            remove_after = 0
    inlier = (pb.weights > 0) & st.inside
    res = torch.where(st.inside[:, None], r, torch.nan)
    e = r.norm(dim=-1)[inlier]
    out_model = model.with_grid(st.grid.cpu().numpy())
    coverage = cell_coverage(out_model, st.u[inlier].cpu().numpy())
    warnings = coverage_warnings(out_model, coverage)
    for line in warnings:
        log.info(line)
    Rn, tn = st.R.cpu().numpy(), st.t.cpu().numpy()
    return BundleResult(
        model=out_model,
        poses=[Pose(orthonormal(Rn[f]), tn[f]) for f in range(F)],
        shifts=st.s.cpu().numpy(), residuals=res.cpu().numpy(), inlier=inlier.cpu().numpy(),
        median_error=float(torch.median(e)) if len(e) else math.nan,
        rms_error=float(torch.sqrt(torch.mean(e * e))) if len(e) else math.nan,
        iterations=it, cost=cost, seconds=time.perf_counter() - t_wall,
        cpu_seconds=time.process_time() - t_cpu, warnings=warnings, coverage=coverage,
        data=BundleData(fr_np, P, p, pb.weights.cpu().numpy(), free_np, settings, pb.pitch),
        theta=None if st.theta is None else st.theta.cpu().numpy())
