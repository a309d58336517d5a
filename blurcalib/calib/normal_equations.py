"""The bundle adjustment's normal equations at its solution: the information of the projection
uncertainty and the cameras without given frames.

:func:`normal_equations` rebuilds the Gauss-Newton blocks of :func:`blurcalib.calib.bundle.bundle_adjust`'s
objective at its solution, data and priors apart, for the projection uncertainty
(:mod:`blurcalib.calib.uncertainty`); :func:`leave_out_models` gives the cameras without given
sets of frames, one step each from the solution, for the held-out validation
(:mod:`blurcalib.calib.validation`). Tensors are torch float64 on the bundle adjustment's device;
pixels follow OpenCV's convention.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike

from blurcalib.calib.bundle import BundleResult, gauge_rotation, reduce_frames
from blurcalib.calib.bundle_problem import (
    BundleProblem,
    BundleState,
    add_priors,
    add_shift_prior,
    add_smoothness_prior,
    data_equations,
    robust_weights,
)
from blurcalib.calib.spd_solve import solve_lower
from blurcalib.camera.generic import CentralGeneric, apply_update, tangent_basis

__all__ = ["NormalEquations", "leave_out_models", "normal_equations"]


@dataclass(eq=False)
class NormalEquations:
    """Gauss-Newton blocks of :func:`bundle_adjust`'s objective at its solution, data and priors apart.

    With the per-observation IRLS weights ``W`` (observation weight times Huber weight) and the
    Jacobians of the residuals in the grid parameters ``J_g`` and in the per-frame blocks ``J_f``
    (rotation increment, translation, shift: 8 columns)::

        hgg_data = J_g^T W J_g,  hgf_data = J_g^T W J_f,  hff_data = J_f^T W J_f

    and the priors' Hessians (costs in px^2, as the objective's): ``hgg_prior`` the smoothness
    prior, ``hff_prior`` the shift prior. A frame whose shift is not free has its shift rows and
    columns zero in the data blocks and an identity in ``hff_prior`` (it is decoupled). Tensors
    are torch float64 on the bundle adjustment's device.

    Attributes:
        hgg_data, hgg_prior: ``(G, G)`` with ``G = 2 GW GH``.
        hgf_data: ``(G, F, 8)``.
        hff_data, hff_prior: ``(F, 8, 8)``.
        weighted_sq: ``sum_i W_i |r_i|^2`` over the inliers (px^2).
        observations: number of inliers ``N`` (each gives 2 residuals).
    """

    hgg_data: torch.Tensor
    hgg_prior: torch.Tensor
    hgf_data: torch.Tensor
    hff_data: torch.Tensor
    hff_prior: torch.Tensor
    weighted_sq: float
    observations: int


def _at_solution(result: BundleResult) -> tuple[BundleProblem, BundleState, torch.Tensor, torch.Tensor]:
    """``result``'s problem and state at its solution, the IRLS weights ``w (N,)`` (observation
    weight times Huber weight, 0 outside the inliers) and the residuals ``r (N, 2)`` (0 there)."""
    data = result.data
    settings = data.settings
    dev = torch.device(settings.device)
    kw: dict[str, Any] = {"dtype": torch.float64, "device": dev}
    spline = result.model.spline(dev)
    pb = BundleProblem(spline, torch.as_tensor(data.frame, device=dev), torch.as_tensor(data.points, **kw),
                  torch.as_tensor(data.observed, **kw), torch.as_tensor(data.weights, **kw),
                  torch.as_tensor(data.shift_free, device=dev), settings)
    pb.smooth_w = 1.0 / (settings.smoothness_px * data.angular_pitch) ** 2
    inlier = torch.as_tensor(result.inlier, device=dev)
    r = torch.where(inlier[:, None], torch.as_tensor(np.nan_to_num(result.residuals), **kw), 0.0)
    s = torch.as_tensor(result.shifts, **kw)
    u = torch.where(inlier[:, None], pb.observed - r - s[pb.frame], 0.0)
    R = torch.as_tensor(np.stack([q.R for q in result.poses]), **kw)
    t = torch.as_tensor(np.stack([q.t for q in result.poses]), **kw)
    st = BundleState(spline.grid, spline.grid, R, t, s, u, inlier)
    w = pb.weights * inlier.to(torch.float64) * robust_weights(r, settings.huber_px)
    return pb, st, w, r


def normal_equations(result: BundleResult) -> NormalEquations:
    """The Gauss-Newton blocks of ``result``'s objective at its solution (:class:`NormalEquations`).

    Built with the final inlier set and the Huber IRLS weights of the final residuals; no
    Levenberg-Marquardt damping.
    """
    pb, st, w, r = _at_solution(result)
    Hgg, Hgf, Hff, bg, bf, tang = data_equations(pb, st, w, r)
    fixed = ~pb.shift_free
    Hff[fixed, 6:, :] = 0.0
    Hff[fixed, :, 6:] = 0.0
    Hgg_p = torch.zeros_like(Hgg)
    Hff_p = torch.zeros_like(Hff)
    add_priors(pb, st, tang, Hgg_p, torch.zeros_like(bg), Hff_p, torch.zeros_like(bf))
    return NormalEquations(Hgg, Hgg_p, Hgf, Hff, Hff_p, float((w * (r * r).sum(-1)).sum()),
                           int(st.inside.sum()))


def _frames_problem(pb: BundleProblem, st: BundleState, frames: torch.Tensor, rows: torch.Tensor
                    ) -> tuple[BundleProblem, BundleState]:
    """The problem and state of the frames ``(F,)`` bool alone, with the observations ``rows (N,)``
    bool (of those frames), the frames renumbered in order: their normal equations without the
    ``(G, F, 8)`` blocks of the other frames."""
    number = torch.cumsum(frames.to(torch.long), 0) - 1
    sub = BundleProblem(pb.spline, number[pb.frame[rows]], pb.points[rows], pb.observed[rows],
                        pb.weights[rows], pb.shift_free[frames], pb.settings)
    sub.smooth_w = pb.smooth_w
    return sub, replace(st, R=st.R[frames], t=st.t[frames], s=st.s[frames], u=st.u[rows],
                        inside=st.inside[rows])


def _leading_partition(sets: Sequence[np.ndarray]) -> int:
    """The number of leading sets ``(F,)`` bool that partition the frames (pairwise disjoint,
    together all frames): the folds; 0 when they do not."""
    seen = np.zeros_like(sets[0]) if sets else np.zeros(0, dtype=bool)
    for k, m in enumerate(sets):
        if (seen & m).any():
            return 0
        seen |= m
        if seen.all():
            return k + 1
    return 0


def leave_out_models(result: BundleResult, left_out: Sequence[ArrayLike], priors: Sequence[CentralGeneric],
                     damping: float = 1e-6) -> list[CentralGeneric]:
    """The camera without each set of frames, one damped Gauss-Newton step from ``result``.

    ``left_out[k] (F,)`` bool marks the frames camera ``k`` must not see; camera ``k`` is the grid
    of the step, from ``result``'s solution (grid, poses and shifts), of :func:`bundle_adjust`'s
    objective over the other frames, its smoothness prior holding ``priors[k]``'s shape. The
    objective's observations are ``result``'s inliers with their IRLS weights at the solution.
    The frames of a set ``L`` add their own terms to the reduced camera system
    (:func:`reduce_frames`; their poses and shifts eliminated)::

        S_L = Hgg_L - sum_{f in L} Hgp_f Hpp_f^-1 Hgp_f^T,   c_L = bg_L - sum_{f in L} Hgp_f Hpp_f^-1 bp_f

    so leaving ``L`` out subtracts its terms from those of all frames::

        (S_all - S_L + H_prior + lambda diag) dg = c_all - c_L + b_prior(priors[k])

    with Marquardt's damping ``lambda = damping`` on the kept data's diagonal (as the first step of
    :func:`bundle_adjust`, no acceptance test). The grid is updated in its tangent parameters
    and re-gauged as :func:`bundle_adjust` does. The cost: one pass over each set's observations
    (the sums of the leading sets' terms give all frames' when those sets partition the frames,
    as k folds do; else one more pass over all observations) and one ``(G, G)`` solve per camera
    (:func:`blurcalib.calib.spd_solve.solve_lower`), instead of a refit each.

    Raises:
        ValueError: a set not of shape ``(F,)``, not one prior per set, or a prior on another grid.
    """
    pb, st, w, r = _at_solution(result)
    F = pb.num_frames
    sets = [np.asarray(m, dtype=bool).reshape(-1) for m in left_out]
    if len(sets) != len(priors) or any(m.shape != (F,) for m in sets):
        raise ValueError(f"need one prior and one ({F},) frame mask per camera; got {len(priors)} "
                         f"priors and {len(sets)} masks")
    if any((p.grid_height, p.grid_width) != pb.spline.shape for p in priors):
        raise ValueError(f"every prior must have the model's {pb.gh} x {pb.gw} grid")
    dev = st.grid.device
    kw: dict[str, Any] = {"dtype": st.R.dtype, "device": dev}
    G = 2 * pb.gh * pb.gw
    eye8 = torch.eye(8, **kw)

    def terms(frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``S_L, c_L`` and the data diagonal of ``Hgg_L`` of the frames ``(F,)`` bool, from
        those frames' observations and blocks alone (:func:`_frames_problem`)."""
        rows = frames[pb.frame] & (w > 0)
        if not bool(rows.any()):
            return torch.zeros(G, G, **kw), torch.zeros(G, **kw), torch.zeros(G, **kw)
        sub, sub_st = _frames_problem(pb, st, frames, rows)
        Hgg, Hgp, Hpp, bg, bp, _ = data_equations(sub, sub_st, w[rows], r[rows])
        add_shift_prior(sub, sub_st, Hpp, bp)
        Hpp = Hpp + damping * torch.diag_embed(torch.diagonal(Hpp, dim1=1, dim2=2)) + 1e-12 * eye8
        diag = torch.diagonal(Hgg).clone()
        Hpp_inv = torch.cholesky_inverse(torch.linalg.cholesky(Hpp))
        S, c = reduce_frames(Hgg, Hgp, Hpp_inv, bg, bp, lower=True, overwrite=True)
        assert c is not None  # bg given
        return S, c, diag

    parts: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None] = [
        terms(torch.as_tensor(m, device=dev)) for m in sets[:_leading_partition(sets)]]
    if parts:  # the folds partition the frames: all frames' terms are their sums
        first = parts[0]
        assert first is not None  # parts are freed only below
        S_all, c_all, d_all = (v.clone() for v in first)
        for part in parts[1:]:
            assert part is not None
            S_k, c_k, d_k = part
            S_all += S_k
            c_all += c_k
            d_all += d_k
    else:
        S_all, c_all, d_all = terms(torch.ones(F, dtype=torch.bool, device=dev))
    tang = tangent_basis(st.grid.reshape(-1, 3))
    before = torch.diagonal(S_all).clone()
    add_smoothness_prior(pb, st, tang, S_all, torch.zeros(G, **kw))
    d_all += torch.diagonal(S_all) - before  # the prior's diagonal
    models = []
    for k, (mask, prior) in enumerate(zip(sets, priors, strict=True)):
        part = parts[k] if k < len(parts) else terms(torch.as_tensor(mask, device=dev))
        assert part is not None  # each set's terms are used once
        S, c, d = part
        if k < len(parts):
            parts[k] = None
        S = torch.sub(S_all, S, out=S)
        diag = d_all - d
        S.diagonal().add_(damping * diag + 1e-12 * float(diag.mean()))
        prior_grid = prior.spline(dev).grid
        grid0 = prior_grid @ gauge_rotation(pb.spline, prior_grid).T
        rhs = c_all - c
        add_smoothness_prior(pb, replace(st, grid0=grid0), tang, None, rhs)
        dg = solve_lower(S, rhs)
        del S
        grid = apply_update(st.grid, dg.reshape(pb.gh, pb.gw, 2))
        grid = grid @ gauge_rotation(pb.spline, grid).T
        models.append(result.model.with_grid(grid.cpu().numpy()))
    return models
