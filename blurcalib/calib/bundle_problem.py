"""The least-squares problem of the generic bundle adjustment (:mod:`blurcalib.calib.bundle`): its
unknowns (:class:`BundleState`), its fixed data and objective (:class:`BundleProblem`), and its
Gauss-Newton blocks (:func:`normal_equations`).

Residuals ``r_i = p_i - pi_G(X_i) - s_f`` (px) of observation ``i`` of frame ``f``, ``X_i`` its
camera point (:meth:`BundleProblem.rolling_camera_points`), with Huber's loss on ``|r_i|`` by
iteratively reweighted least squares (:func:`robust_weights`); priors on the grid's second
differences, the free shifts and the rolling parameters. The blocks: ``Hgg (G, G)`` of the ``G =
2 GW GH`` grid parameters, ``Hgp (G, F, K)``, the per-frame ``Hpp (F, K, K)`` of ``omega (3), dt
(3), s (2)`` and, with rolling rows, ``theta (12)`` (``K`` 8 or 20), and the right-hand sides
``bg (G,)``, ``bp (F, K)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from blurcalib.calib.frame_block import (
    RollingRows,
    frame_jacobian,
    rolling_frame_jacobian,
    rolling_points,
    rolling_prior_weights,
)
from blurcalib.camera.generic import (
    GridSpline,
    accumulate_blocks,
    param_columns,
    projection_jacobians,
    tangent_basis,
)

if TYPE_CHECKING:
    from blurcalib.calib.bundle import BundleSettings

__all__ = ["BundleProblem", "BundleState", "add_priors", "add_rolling_prior", "add_shift_prior",
           "add_smoothness_prior", "data_equations", "normal_equations", "robust_weights"]

OBSERVATION_CHUNK = 16384
"""Observations whose Jacobian products are formed at once when the normal equations are
accumulated (memory per chunk about 16 kB per observation)."""


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
                s: torch.Tensor, init: torch.Tensor | None, theta: torch.Tensor | None = None
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
    i, j, k = (torch.cat([a, b]) for a, b in zip(rows, cols, strict=True))
    return i, j, k


def robust_weights(r: torch.Tensor, huber_px: float) -> torch.Tensor:
    """IRLS weights of Huber's loss on the residual norm: 1 inside, ``delta / e`` beyond."""
    e = r.norm(dim=-1)
    return torch.where(e <= huber_px, torch.ones_like(e), huber_px / e.clamp_min(1e-300))


def normal_equations(pb: BundleProblem, st: BundleState, w: torch.Tensor, r: torch.Tensor
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
    """The observations' part of :func:`normal_equations` (no priors).

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
    for sel in torch.nonzero(w > 0).squeeze(1).split(OBSERVATION_CHUNK):  # type: ignore[no-untyped-call]
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
