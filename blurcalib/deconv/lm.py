"""The Levenberg-Marquardt loop of the block solver on ``(H, alpha)``, the kernel projected out."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from blurcalib.deconv.latent import update_homography
from blurcalib.deconv.problem import BlockProblem, Design, KernelSolve


@dataclass
class LmStage:
    """The result of :func:`lm_stage` for ``b`` blocks.

    Attributes:
        H_loc: ``(b, 3, 3)`` float64 the best homographies (latent-local px).
        alpha: ``(b, 2)`` float64 the best relative brightness gradients ``(a1, a2) / a3``.
        solve: the kernel sub-problem at the best point.
        move: ``(b,)`` px, how far the last accepted step moved the star-centre estimate (0 if
            none was accepted).
    """

    H_loc: torch.Tensor
    alpha: torch.Tensor
    solve: KernelSolve
    move: torch.Tensor


CHORD_FROM_STEP = 1
"""First LM step at which a fit with given kernels may take chord steps (:func:`_chord`): its
trial point is evaluated without the Jacobian, the 8 convolutions that are most of a solve."""

CHORD_WITHIN_PX = 0.02
"""A block that accepts a chord-eligible step keeps the Jacobian of its last full evaluation
while its star-centre estimate stays within this distance (px) of that evaluation's; farther,
the Jacobian is evaluated at the new point. Measured on the heavily blurred frames of
``scripts/bench_yield.py`` (4 runs, the frames as they are and perturbed): see docs/deconvolution.md
("Speed"). Without the limit, blocks started 1.5 px off ended up to 0.05 px from the fit that
evaluates every Jacobian, at up to 12 % more loss after 6 steps; with it, within 0.004 px."""


def lm_stage(prob: BlockProblem, H_loc: torch.Tensor, alpha: torch.Tensor, des: Design, steps: int
             ) -> LmStage:
    """Levenberg-Marquardt on ``(H, alpha)`` with ``(k~, b)`` projected out (variable projection).

    Each step costs one kernel solve (:meth:`BlockProblem.evaluate`); a step that does not lower
    the objective is undone and retried from the best point with a larger damping. A block stops
    once its step's predicted decrease ``delta^T (2 g - N delta)`` is below
    :attr:`DeconvSettings.stop_decrease` times its residual variance ``sse / n`` (the step is a
    small fraction of the fit's own standard deviation); the later steps solve only the blocks
    still going. With given kernels (``des.fixed``), from step :data:`CHORD_FROM_STEP` on, the
    steps are chord steps (:func:`_chord`): the Jacobian's 8 convolutions are most of a solve.
    """
    b = H_loc.shape[0]
    dev = H_loc.device
    best = prob.evaluate(H_loc, alpha, des, None, with_jac=steps > 0)
    H_best, a_best = H_loc.clone(), alpha.clone()  # updated in place, row by row
    c_best = prob.centre_estimate(H_best, best.x, des)
    c_jac = c_best.clone()  # where each block's Jacobian was last evaluated
    move = torch.zeros(b, dtype=torch.float64, device=dev)
    mu = torch.full((b,), 1e-3, device=dev, dtype=torch.float64)
    going = torch.ones(b, dtype=torch.bool, device=dev)
    rejected = torch.zeros(b, dtype=torch.int64, device=dev)  # steps rejected in a row
    npix = des.pix_w.sum(dim=1).double().clamp_min(1.0)
    for it in range(steps):
        diag = best.N.diagonal(dim1=1, dim2=2)
        A = best.N + torch.diag_embed(mu[:, None] * diag + 1e-12 * diag.mean(1, keepdim=True) + 1e-30)
        delta = torch.nan_to_num(torch.linalg.solve_ex(A, best.g[..., None])[0][..., 0])
        decrease = (delta * (2.0 * best.g - (best.N @ delta[..., None])[..., 0])).sum(dim=1)
        going &= (decrease > prob.s.stop_decrease * best.sse / npix) & (rejected < prob.s.stop_rejections)
        rows = torch.nonzero(going)[:, 0]
        if rows.numel() == 0:
            break
        sub = des if rows.numel() == b else des.take(rows)
        H_try = update_homography(H_best[rows], delta[rows, :8])
        a_try = a_best[rows] + delta[rows, 8:10]
        jac = it < steps - 1
        chord = jac and it >= CHORD_FROM_STEP and des.fixed is not None
        prev = best if rows.numel() == b else best.take(rows)
        cur = prob.evaluate(H_try, a_try, sub, prev.lam, with_jac=jac and not chord)
        accept = torch.isfinite(cur.obj) & (cur.obj < prev.obj)
        c_try = prob.centre_estimate(H_try, cur.x, sub)
        fresh = accept  # the accepted blocks whose Jacobian is evaluated at the trial point
        if chord:
            fresh = accept & (torch.linalg.norm(c_try - c_jac[rows], dim=1) > CHORD_WITHIN_PX)
            cur = _chord(prob, cur, prev, accept, fresh, H_try, a_try, sub)
        c_jac[rows[fresh]] = c_try[fresh]
        won = rows[accept]
        H_best[won], a_best[won] = H_try[accept], a_try[accept]
        move[won] = torch.linalg.norm(c_try[accept] - c_best[won], dim=1)
        c_best[won] = c_try[accept]
        best.put(won, cur.take(accept))
        mu[rows] = torch.where(accept, mu[rows] / 3.0, mu[rows] * 4.0)
        rejected[rows] = torch.where(accept, 0, rejected[rows] + 1)
    return LmStage(H_best, a_best, best, move)


def _chord(prob: BlockProblem, cur: KernelSolve, best: KernelSolve, accept: torch.Tensor, fresh: torch.Tensor,
           H_loc: torch.Tensor, alpha: torch.Tensor, des: Design) -> KernelSolve:
    """``cur``, a trial point's solve with given kernels evaluated without its Jacobian, given the
    Gauss-Newton systems of the blocks that accept it (``accept (b,)``): for those in ``fresh``
    evaluated at ``(H_loc, alpha)``; for the others a chord step's, ``best``'s Jacobian
    ``J (b, 10, n)`` scaled by the ratio of their contrasts ``a3`` (the model is ``a3 (k * S)``),
    so ``N`` by its square, and ``g = J r`` with the trial's residual ``r``. The blocks that
    reject it keep ``best``'s system, the point they step from again."""
    N, g, J = best.N.clone(), best.g.clone(), best.J.clone()
    rows = torch.nonzero(accept & ~fresh)[:, 0]
    if rows.numel():
        scale = (cur.x[rows, :1] / best.x[rows, :1]).to(J.dtype)
        J[rows] = J[rows] * scale[:, :, None]
        N[rows] = N[rows] * (scale.double() ** 2)[:, :, None]
        g[rows] = (J[rows] @ cur.res[rows][..., None]).double()[..., 0]
    rows = torch.nonzero(fresh)[:, 0]
    if rows.numel():
        part = prob.evaluate(H_loc[rows], alpha[rows], des.take(rows), best.lam[rows], with_jac=True)
        N[rows], g[rows], J[rows] = part.N, part.g, part.J
    return replace(cur, N=N, g=g, J=J)
