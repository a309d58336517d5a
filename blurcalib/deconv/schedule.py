"""The solver's schedule on one padded batch of blocks: coarse kernel, stages, re-centring.

Stages (the module docstring of :mod:`blurcalib.deconv.blocks`): a coarse kernel at ``H0``;
``outer_iterations`` times integer re-centring, a kernel support and LM steps
(:func:`blurcalib.deconv.lm.lm_stage`); then the sub-pixel re-centring. After the coarse kernel
the blocks are solved in groups of similar kernel support (:func:`stage_groups`). Blocks with an
expected PSF start from its support (:func:`fit_hinted_batch`); blocks with a given PSF only fit
``H`` and the brightness (:func:`fit_fixed_batch`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch

from blurcalib.deconv.linear import kernel_support
from blurcalib.deconv.lm import lm_stage
from blurcalib.deconv.problem import BlockProblem
from blurcalib.psf.kernel import recentre


@dataclass
class BatchFit:
    """Per-block results of one batch (``b`` blocks, ``K`` the kernel size), numpy.

    Attributes:
        H: ``(b, 3, 3)`` homographies after the sub-pixel re-centring (``H[2, 2] = 1``).
        psf: ``(b, K, K)`` re-centred kernels; psf_fit: ``(b, K, K)`` the fitted ones.
        coeffs: ``(b, 6)`` ``(a1, a2, a3, b1, b2, b3)`` grey levels.
        loss: ``(b,)`` mean squared residual (grey levels^2).
        centroid: ``(b, 2)`` px, the centroid of ``psf_fit`` that the re-centring moved ``H`` by.
        num_pixels: ``(b,)`` pixels in the loss.
        centre_step: ``(b,)`` px, the star centre's movement in the last accepted LM step.
        masks: ``b`` bool ``(height, width)`` arrays, the loss's pixels over each window.
    """

    H: np.ndarray
    psf: np.ndarray
    psf_fit: np.ndarray
    coeffs: np.ndarray
    loss: np.ndarray
    centroid: np.ndarray
    num_pixels: np.ndarray
    centre_step: np.ndarray
    masks: list[np.ndarray]

    @staticmethod
    def merge(parts: list[BatchFit], groups: list[np.ndarray]) -> BatchFit:
        """The results of the stage groups ``groups`` (block indices) back in the batch's order."""
        inverse = np.argsort(np.concatenate(groups))
        values: dict[str, Any] = {}
        for f in fields(BatchFit):
            if f.name == "masks":
                masks = [m for part in parts for m in part.masks]
                values[f.name] = [masks[i] for i in inverse]
            else:
                values[f.name] = np.concatenate([getattr(part, f.name) for part in parts])[inverse]
        return BatchFit(**values)


_GROUP_COST = 8.6e7
"""Fixed cost of solving one more stage group (its Python-level tensor operations), in units of
the multiply-adds of a normal matrix ``D D^T``: about 3 ms a kernel solve against about 0.035 ns
a multiply-add on one CPU thread."""
_LATENT_COST = 4.3e3
"""Cost of one latent-grid pixel of a kernel solve (the pattern, its Jacobian and the
convolutions: about 150 ns with FFT convolutions), in the same units."""


def stage_groups(support: np.ndarray, pixels: np.ndarray, size: np.ndarray, radius: int, most: int
                  ) -> list[np.ndarray]:
    """Blocks sorted by kernel support, cut into consecutive groups of at most ``most`` blocks.

    A group is padded to its largest support ``m``, loss pixel count ``n`` and window; the cuts
    minimise the modelled cost of its kernel solves, ``sum over groups of (blocks x ((m + 3)^2 n
    + _LATENT_COST x latent pixels) + _GROUP_COST)`` (dynamic programming over the sorted order).

    Args:
        support: ``(b,)`` kernel entries per block; pixels: ``(b,)`` loss pixels per block;
            size: ``(b, 2)`` window ``(w, h)`` px; radius: kernel radius ``c`` px;
            most: the largest group.
    Returns:
        The groups, as arrays of block indices.
    """
    order = np.argsort(support, kind="stable")
    rows = (support[order] + 3).tolist(), pixels[order].tolist(), (size[order] + 2 * radius).tolist()
    b = len(order)
    best = [0.0] + [math.inf] * b
    cut = [0] * (b + 1)
    for end in range(1, b + 1):
        m = n = w = h = 0
        for start in range(end - 1, max(end - most, 0) - 1, -1):
            m, n = max(m, rows[0][start]), max(n, rows[1][start])
            w, h = max(w, rows[2][start][0]), max(h, rows[2][start][1])
            cost = best[start] + (end - start) * (m * m * n + _LATENT_COST * w * h) + _GROUP_COST
            if cost < best[end]:
                best[end], cut[end] = cost, start
    groups = []
    end = b
    while end > 0:
        groups.append(order[cut[end]:end])
        end = cut[end]
    return groups[::-1]


def fit_free_batch(prob: BlockProblem, H: np.ndarray) -> BatchFit:
    """The full schedule on one padded batch from homographies ``H (b, 3, 3)`` (image px): the
    coarse kernel, integer re-centring, then :attr:`DeconvSettings.outer_iterations` stages in
    groups of similar kernel support."""
    b = H.shape[0]
    H_loc = prob.to_local(H)
    alpha = torch.zeros((b, 2), dtype=torch.float64, device=H_loc.device)
    des = prob.design(H_loc, None)
    k = prob.kernel(prob.evaluate(H_loc, alpha, des, None, with_jac=False).x, des)
    H_loc, n = prob.recentre_int(H_loc, k)
    return _fit_groups(prob, H_loc, prob.support(k, n), des.mask.sum(dim=(1, 2)), prob.s.outer_iterations)


def fit_hinted_batch(prob: BlockProblem, H: np.ndarray, hint: torch.Tensor) -> BatchFit:
    """The schedule from expected PSFs ``hint (b, K, K)``: their support is the first, no coarse
    kernel, :attr:`DeconvSettings.hinted_stages` stages."""
    s = prob.s
    H_loc = prob.to_local(H)
    support = kernel_support(hint, s.support_threshold, s.support_dilation)
    return _fit_groups(prob, H_loc, support, prob.square_mask(H_loc).sum(dim=(1, 2)), s.hinted_stages)


def fit_fixed_batch(prob: BlockProblem, H: np.ndarray, fixed: torch.Tensor) -> BatchFit:
    """One stage of :attr:`DeconvSettings.fixed_steps` LM steps with the given kernels
    ``fixed (b, K, K)`` held: ``H`` and the brightness are fitted."""
    H_loc = prob.to_local(H)
    groups = stage_groups(np.ones(H.shape[0]), prob.square_mask(H_loc).sum(dim=(1, 2)).cpu().numpy(),
                          prob.size, prob.r, prob.s.stage_batch_size)
    parts = [_fit_stages(prob.subset(idx), H_loc[t], None, 1, fixed[t])
             for idx in groups for t in [torch.as_tensor(idx, device=H_loc.device)]]
    return BatchFit.merge(parts, groups)


def _fit_groups(prob: BlockProblem, H_loc: torch.Tensor, support: torch.Tensor, pixels: torch.Tensor,
                stages: int) -> BatchFit:
    """``stages`` stages from ``H_loc`` and the first kernel ``support (b, K, K)``, in groups of
    similar support (:func:`stage_groups`, ``pixels (b,)`` the loss's pixels per block)."""
    groups = stage_groups(support.sum(dim=(1, 2)).cpu().numpy(), pixels.cpu().numpy(), prob.size, prob.r,
                          prob.s.stage_batch_size)
    parts = []
    for idx in groups:
        t = torch.as_tensor(idx, device=H_loc.device)
        parts.append(_fit_stages(prob.subset(idx), H_loc[t], support[t], stages))
    return BatchFit.merge(parts, groups)


def _fit_stages(prob: BlockProblem, H_loc: torch.Tensor, support: torch.Tensor | None, stages: int,
                fixed: torch.Tensor | None = None) -> BatchFit:
    """``stages`` stages from an integer re-centred ``H_loc`` and its first kernel ``support``
    (or with the given kernels ``fixed``), then the sub-pixel re-centring."""
    s = prob.s
    alpha = torch.zeros((H_loc.shape[0], 2), dtype=torch.float64, device=H_loc.device)
    steps = s.gn_steps if fixed is None else s.fixed_steps
    for stage in range(stages):
        des = prob.design(H_loc, support, fixed)
        lm = lm_stage(prob, H_loc, alpha, des, steps)
        H_loc, alpha = lm.H_loc, lm.alpha
        k = prob.kernel(lm.solve.x, des)
        if stage < stages - 1:
            H_loc, n = prob.recentre_int(H_loc, k)
            support = prob.support(k, n)
    x = lm.solve.x.cpu().numpy()
    H_fit = prob.to_image(H_loc)
    k_t = k.cpu().numpy()
    a3 = k_t.sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        k_fit = k_t / a3[:, None, None]
    H_rc, psf, centroid = recentre(H_fit, k_fit, s.centroid_threshold)
    alpha_np = alpha.cpu().numpy()
    coeffs = np.stack([alpha_np[:, 0] * a3, alpha_np[:, 1] * a3, a3, x[:, -3], x[:, -2], x[:, -1]], axis=1)
    npix = des.mask.sum(dim=(1, 2)).cpu().numpy()
    masks = des.mask.cpu().numpy()
    return BatchFit(H=H_rc / H_rc[:, 2:, 2:], psf=psf, psf_fit=k_fit, coeffs=coeffs,
                    loss=lm.solve.sse.cpu().numpy() / np.maximum(npix, 1), centroid=centroid, num_pixels=npix,
                    centre_step=lm.move.cpu().numpy(),
                    masks=[masks[i, :sz[1], :sz[0]] for i, sz in enumerate(prob.size)])
