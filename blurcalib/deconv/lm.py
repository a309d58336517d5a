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


SPLIT_FROM_STEP = 1
"""First LM step whose trial Jacobian is computed only where the step is accepted (fits with
given kernels). Measured on heavily blurred frames: 97 % of the blocks accept their first step,
82 % the second, 58 % the third and 15-31 % the later ones; the split costs one more convolution
per accepting block (of 9), so it pays from the second step."""


def lm_stage(prob: BlockProblem, H_loc: torch.Tensor, alpha: torch.Tensor, des: Design, steps: int
             ) -> LmStage:
    """Levenberg-Marquardt on ``(H, alpha)`` with ``(k~, b)`` projected out (variable projection).

    Each step costs one kernel solve (:meth:`BlockProblem.evaluate`); a step that does not lower
    the objective is undone and retried from the best point with a larger damping. A block stops
    once its step's predicted decrease ``delta^T (2 g - N delta)`` is below
    :attr:`DeconvSettings.stop_decrease` times its residual variance ``sse / n`` (the step is a
    small fraction of the fit's own standard deviation); the later steps solve only the blocks
    still going. With given kernels (``des.fixed``), from the second step on, a trial point's
    Jacobian is computed only for the blocks that accept it (:func:`_jacobian_where`): most
    blocks reject their later steps, and the Jacobian's 8 convolutions are most of a solve.
    """
    b = H_loc.shape[0]
    dev = H_loc.device
    best = prob.evaluate(H_loc, alpha, des, None, with_jac=steps > 0)
    H_best, a_best = H_loc.clone(), alpha.clone()  # updated in place, row by row
    c_best = prob.centre_estimate(H_best, best.x, des)
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
        split = jac and it >= SPLIT_FROM_STEP and des.fixed is not None
        prev = best if rows.numel() == b else best.take(rows)
        cur = prob.evaluate(H_try, a_try, sub, prev.lam, with_jac=jac and not split)
        accept = torch.isfinite(cur.obj) & (cur.obj < prev.obj)
        if split:
            cur = _jacobian_where(prob, cur, prev, accept, H_try, a_try, sub)
        c_try = prob.centre_estimate(H_try, cur.x, sub)
        won = rows[accept]
        H_best[won], a_best[won] = H_try[accept], a_try[accept]
        move[won] = torch.linalg.norm(c_try[accept] - c_best[won], dim=1)
        c_best[won] = c_try[accept]
        best.put(won, cur.take(accept))
        mu[rows] = torch.where(accept, mu[rows] / 3.0, mu[rows] * 4.0)
        rejected[rows] = torch.where(accept, 0, rejected[rows] + 1)
    return LmStage(H_best, a_best, best, move)


def _jacobian_where(prob: BlockProblem, cur: KernelSolve, best: KernelSolve, accept: torch.Tensor,
                    H_loc: torch.Tensor, alpha: torch.Tensor, des: Design) -> KernelSolve:
    """``cur``, a trial point's solve without its Jacobian, with the Gauss-Newton system ``N, g``
    of the blocks that accept it (``accept (b,)``) evaluated at ``(H_loc, alpha)`` for those
    blocks alone; the other blocks keep ``best``'s, the point they step from again."""
    rows = torch.nonzero(accept)[:, 0]
    N, g = best.N.clone(), best.g.clone()
    if rows.numel():
        part = prob.evaluate(H_loc[rows], alpha[rows], des.take(rows), best.lam[rows], with_jac=True)
        N[rows], g[rows] = part.N, part.g
    return replace(cur, N=N, g=g)
