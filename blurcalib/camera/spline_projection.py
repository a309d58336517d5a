"""The projection of a central generic camera (:meth:`blurcalib.camera.generic.GridSpline.project`)
as a batched least-squares problem of :func:`blurcalib.optim.lm.run_batch`: one 2-unknown fit per
point, ``min_u |d(u) - p / |p||^2`` (OpenCV px), clamped to the calibrated area."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from blurcalib.optim.lm import Damping

if TYPE_CHECKING:
    from blurcalib.camera.generic import GridSpline


PROJECTION_DAMPING = Damping(start=1.0, shrink=2.0, grow=4.0)
"""The damping of :meth:`GridSpline.project`: halved after an accepted step, x4 after a rejected one
(its start is given per point)."""


class SplineProjection:
    """The points of :meth:`GridSpline.project` as a batched least-squares problem
    (:class:`blurcalib.optim.lm.BatchProblem`): per point its pixel ``u``, the residual
    ``d(u) - p`` and its derivative ``D (N, 3, 2)``, and the step and trial of the points going."""

    def __init__(self, spline: GridSpline, p: torch.Tensor, u: torch.Tensor, tol_px: float,
                 edge_iterations: int) -> None:
        self.spline, self.p, self.u, self.tol_px = spline, p, u, tol_px
        self.edge_iterations = edge_iterations
        ev = spline.evaluate(u)
        self.D = ev.dd_du
        self.r = ev.d - p
        self._cost = (self.r * self.r).sum(-1)
        self.on_edge = torch.zeros(len(u), dtype=torch.long, device=u.device)

    @property
    def cost(self) -> torch.Tensor:
        return self._cost

    def solve(self, lam: torch.Tensor, going: torch.Tensor) -> torch.Tensor:
        """The damped 2 x 2 steps of the points going; a point whose step is below ``tol_px`` takes
        it and stops, its residual there linearised (``r - D step``) instead of evaluated."""
        idx = torch.nonzero(going).squeeze(1)
        J = self.D[idx]
        H = J.transpose(1, 2) @ J
        b = (J.transpose(1, 2) @ self.r[idx, :, None]).squeeze(-1)
        lm = lam[idx]
        a00, a01, a11 = H[:, 0, 0] + lm, H[:, 0, 1], H[:, 1, 1] + lm
        det = a00 * a11 - a01 * a01
        step = torch.stack([(a11 * b[:, 0] - a01 * b[:, 1]) / det,
                            (a00 * b[:, 1] - a01 * b[:, 0]) / det], -1)
        small = step.abs().amax(-1) < self.tol_px
        worth = torch.ones_like(going)
        if bool(small.any()):  # converged: the last step is taken without evaluating its end
            done = idx[small]
            self.u[done] = self.spline.clamp(self.u[done] - step[small])
            after = self.r[done] - (J[small] @ step[small, :, None])[..., 0]  # its residual, linearised
            self._cost[done] = (after * after).sum(-1)
            worth[done] = False
            step = step[~small]
        self.step = step
        return worth

    def trial(self, rows: torch.Tensor, index: int, last: bool) -> torch.Tensor:
        self.u_new = self.spline.clamp(self.u[rows] - self.step)
        self.ev_new = self.spline.evaluate(self.u_new)
        self.r_new = self.ev_new.d - self.p[rows]
        self.cost_new = (self.r_new * self.r_new).sum(-1)
        return self.cost_new

    def accept(self, rows: torch.Tensor, accepted: torch.Tensor) -> torch.Tensor:
        """Move the accepted points; the points tried that stop: moved less than ``tol_px``, at a
        zero residual, stalled (an accepted step lowering the cost by at most 1e-10 of it), or held
        at the area's edge for ``edge_iterations`` trials in a row."""
        lo, hi = self.spline.lo, self.spline.hi
        current = self._cost[rows]
        stalled = accepted & (current - self.cost_new <= 1e-10 * current)
        moved = (self.u_new - self.u[rows]).abs().amax(-1)
        acc = rows[accepted]
        self.u[acc] = self.u_new[accepted]
        self.r[acc] = self.r_new[accepted]
        self._cost[acc] = self.cost_new[accepted]
        self.D[acc] = self.ev_new.dd_du[accepted]
        edge = torch.any((self.u[rows] <= lo) | (self.u[rows] >= hi), dim=-1)
        self.on_edge[rows] = torch.where(edge, self.on_edge[rows] + 1, 0)
        return ((moved < self.tol_px) | (self._cost[rows] < 1e-26) | stalled
                | (self.on_edge[rows] >= self.edge_iterations))
