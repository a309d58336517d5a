"""The Levenberg-Marquardt fit of the block solver on ``(H, alpha)``, the kernel projected out."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from blurcalib.deconv.latent import update_homography
from blurcalib.deconv.problem import BlockProblem, Design, KernelSolve
from blurcalib.optim.lm import Damping, LmRule, Stopping, run_batch

DAMPING = Damping(start=1e-3, shrink=3.0, grow=4.0)
"""Each block's damping ``mu`` of ``N + mu diag(N)``: 1e-3, /3 after an accepted step, x4 after a
rejected one."""


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
    """Levenberg-Marquardt on ``(H, alpha)`` with ``(k~, b)`` projected out (variable projection),
    by :func:`blurcalib.optim.lm.run_batch` with a damping per block (:data:`DAMPING`).

    Each step costs one kernel solve (:meth:`BlockProblem.evaluate`); a step that does not lower
    the objective is undone and retried from the best point with a larger damping. A block stops
    once its step's predicted decrease ``delta^T (2 g - N delta)`` is below
    :attr:`DeconvSettings.stop_decrease` times its residual variance ``sse / n`` (the step is a
    small fraction of the fit's own standard deviation), or after
    :attr:`DeconvSettings.stop_rejections` rejected steps in a row; the later steps solve only the
    blocks still going. With given kernels (``des.fixed``), from step :data:`CHORD_FROM_STEP` on,
    the steps are chord steps (:func:`_chord`): the Jacobian's 8 convolutions are most of a solve.
    """
    fit = _BlockFit(prob, H_loc, alpha, des, steps)
    run_batch(fit, LmRule(DAMPING, Stopping(max_trials=steps, max_rejections=prob.s.stop_rejections)))
    return LmStage(fit.H_best, fit.a_best, fit.best, fit.move)


class _BlockFit:
    """The blocks of :func:`lm_stage` as a batched least-squares problem
    (:class:`blurcalib.optim.lm.BatchProblem`): the best point of each block, its kernel solve
    (whose ``N``, ``g`` are its linearisation), and the trial of the blocks going."""

    def __init__(self, prob: BlockProblem, H_loc: torch.Tensor, alpha: torch.Tensor, des: Design,
                 steps: int) -> None:
        self.prob, self.des = prob, des
        self.best = prob.evaluate(H_loc, alpha, des, None, with_jac=steps > 0)
        self.H_best, self.a_best = H_loc.clone(), alpha.clone()  # updated in place, row by row
        self.c_best = prob.centre_estimate(self.H_best, self.best.x, des)
        self.c_jac = self.c_best.clone()  # where each block's Jacobian was last evaluated
        self.move = torch.zeros(H_loc.shape[0], dtype=torch.float64, device=H_loc.device)
        self.npix = des.pix_w.sum(dim=1).double().clamp_min(1.0)

    @property
    def cost(self) -> torch.Tensor:
        return self.best.obj

    def solve(self, lam: torch.Tensor, going: torch.Tensor) -> torch.Tensor:
        """Every block's damped Gauss-Newton step; those whose predicted decrease is worth a trial."""
        best = self.best
        assert best.N is not None and best.g is not None  # evaluated with its Jacobian
        diag = best.N.diagonal(dim1=1, dim2=2)
        A = best.N + torch.diag_embed(lam[:, None] * diag + 1e-12 * diag.mean(1, keepdim=True) + 1e-30)
        self.delta = torch.nan_to_num(torch.linalg.solve_ex(A, best.g[..., None])[0][..., 0])
        decrease = (self.delta * (2.0 * best.g - (best.N @ self.delta[..., None])[..., 0])).sum(dim=1)
        return decrease > self.prob.s.stop_decrease * best.sse / self.npix

    def trial(self, rows: torch.Tensor, index: int, last: bool) -> torch.Tensor:
        b = self.H_best.shape[0]
        self.rows = rows
        self.sub = self.des if rows.numel() == b else self.des.take(rows)
        self.H_try = update_homography(self.H_best[rows], self.delta[rows, :8])
        self.a_try = self.a_best[rows] + self.delta[rows, 8:10]
        jac = not last
        self.chord = jac and index >= CHORD_FROM_STEP and self.des.fixed is not None
        self.prev = self.best if rows.numel() == b else self.best.take(rows)
        self.cur = self.prob.evaluate(self.H_try, self.a_try, self.sub, self.prev.lam,
                                      with_jac=jac and not self.chord)
        return self.cur.obj

    def accept(self, rows: torch.Tensor, accept: torch.Tensor) -> None:
        cur, sub = self.cur, self.sub
        c_try = self.prob.centre_estimate(self.H_try, cur.x, sub)
        fresh = accept  # the accepted blocks whose Jacobian is evaluated at the trial point
        if self.chord:
            fresh = accept & (torch.linalg.norm(c_try - self.c_jac[rows], dim=1) > CHORD_WITHIN_PX)
            cur = _chord(self.prob, cur, self.prev, accept, fresh, self.H_try, self.a_try, sub)
        self.c_jac[rows[fresh]] = c_try[fresh]
        won = rows[accept]
        self.H_best[won], self.a_best[won] = self.H_try[accept], self.a_try[accept]
        self.move[won] = torch.linalg.norm(c_try[accept] - self.c_best[won], dim=1)
        self.c_best[won] = c_try[accept]
        self.best.put(won, cur.take(accept))


def _chord(prob: BlockProblem, cur: KernelSolve, best: KernelSolve, accept: torch.Tensor, fresh: torch.Tensor,
           H_loc: torch.Tensor, alpha: torch.Tensor, des: Design) -> KernelSolve:
    """``cur``, a trial point's solve with given kernels evaluated without its Jacobian, given the
    Gauss-Newton systems of the blocks that accept it (``accept (b,)``): for those in ``fresh``
    evaluated at ``(H_loc, alpha)``; for the others a chord step's, ``best``'s Jacobian
    ``J (b, 10, n)`` scaled by the ratio of their contrasts ``a3`` (the model is ``a3 (k * S)``),
    so ``N`` by its square, and ``g = J r`` with the trial's residual ``r``. The blocks that
    reject it keep ``best``'s system, the point they step from again."""
    assert best.N is not None and best.g is not None and best.J is not None and cur.res is not None
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
        assert part.N is not None and part.g is not None and part.J is not None
        N[rows], g[rows], J[rows] = part.N, part.g, part.J
    return replace(cur, N=N, g=g, J=J)
