"""The linear sub-problem of the block solver: ridge least squares with non-negative kernel entries."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as nnf


@dataclass(frozen=True)
class Factor:
    """The Cholesky factor of a kernel solve's free system, compacted to its free entries.

    ``chol (b, F, F)`` factors ``G`` restricted to ``index (b, F)`` (the free entries first, in
    order, then padding); ``weight (b, F)`` is 1 on free entries and 0 on padding, whose rows
    and columns are the identity.
    """

    chol: torch.Tensor
    index: torch.Tensor
    weight: torch.Tensor

    def solve(self, rhs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``G_FF^{-1} rhs_F`` for ``rhs (b, M, c)``: ``(rhs_F (b, F, c), solution (b, F, c))``."""
        index = self.index[..., None].expand(-1, -1, rhs.shape[2])
        sel = torch.gather(rhs, 1, index) * self.weight[..., None]
        return sel, torch.cholesky_solve(sel, self.chol)


def solve_nonnegative(G: torch.Tensor, rhs: torch.Tensor, m: int, passes: int
                       ) -> tuple[torch.Tensor, Factor]:
    """``x = G^{-1} rhs`` with the first ``m`` entries that come out negative fixed at zero.

    Active-set passes: each fixes the entries that are negative in the previous solution (the
    others are free) and re-solves the free block of ``G`` (Cholesky, ``G`` is symmetric positive
    definite through the ridge), gathered into a ``(b, F, F)`` system over the largest free count
    ``F`` (most kernel entries end fixed, so the later passes are cheap); the passes stop early
    once no block's active set changes.

    Args:
        G: ``(b, M, M)`` float64 normal matrices; rhs: ``(b, M, 1)``; m: constrained entries
            (the kernel's); passes: at most this many active-set passes (0: unconstrained).
    Returns:
        ``x (b, M)`` (fixed entries exactly 0) and the :class:`Factor` of the final free system.
    """
    b, M = rhs.shape[:2]
    dev = G.device
    index = torch.arange(M, device=dev).expand(b, M)
    weight = torch.ones((b, M), dtype=G.dtype, device=dev)
    # cholesky_ex: a bad block must not stop the batch
    factor = Factor(torch.linalg.cholesky_ex(G)[0], index, weight)
    x = torch.cholesky_solve(rhs, factor.chol)[..., 0]
    free = torch.ones((b, M), dtype=torch.bool, device=dev)
    for _ in range(passes):
        keep = free.clone()
        keep[:, :m] &= x[:, :m] > 0
        if torch.equal(keep, free):
            break
        free = keep
        F = int(free.sum(dim=1).max())
        index = torch.argsort((~free).to(torch.int8), dim=1, stable=True)[:, :F]
        weight = torch.gather(free, 1, index).to(G.dtype)
        flat = (index[:, :, None] * M + index[:, None, :]).reshape(b, F * F)
        Gf = torch.gather(G.reshape(b, M * M), 1, flat).reshape(b, F, F)
        Gf *= weight[:, :, None] * weight[:, None, :]
        Gf.diagonal(dim1=1, dim2=2).add_(1.0 - weight)
        factor = Factor(torch.linalg.cholesky_ex(Gf)[0], index, weight)
        xf = factor.solve(rhs)[1][..., 0] * weight
        x = torch.zeros_like(x).scatter_(1, index, xf)
    return x, factor


def kernel_support(k: torch.Tensor, threshold: float, dilation: int) -> torch.Tensor:
    """``(b, K, K)`` bool: the entries of kernels ``k (b, K, K)`` at or above ``threshold`` of
    their peak, dilated by ``dilation`` px (a square structuring element)."""
    core = (k >= threshold * k.amax(dim=(1, 2), keepdim=True)).to(torch.float32)
    return nnf.max_pool2d(core[:, None], 2 * dilation + 1, stride=1, padding=dilation)[:, 0] > 0
