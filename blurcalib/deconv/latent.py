"""The latent pattern ``S(H)`` of a block and its derivative w.r.t. the homography.

``S(H)(x) = sigmoid(d_px(x) / tau)``, ``d_px`` the signed distance in pixels from the pixel centre
``x`` to the nearest pattern edge (sector rays *and* square borders,
:func:`blurcalib.target.star.star_signed_distance` divided by its gradient norm through ``H``),
positive in white: a pixel-consistent soft edge of width ``tau`` px that the PSF absorbs. The
pattern is periodic: beyond the block's square it continues into the neighbouring stars.
"""

from __future__ import annotations

from typing import cast

import torch

from blurcalib.target.star import star_signed_distance_normal


def update_homography(H: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """The block-side update ``H (I + Delta)``, normalised (``H[2, 2] = 1``), for ``H (b, 3, 3)``
    and ``delta (b, 8)``: ``Delta = [[d1, d2, d3], [d4, d5, d6], [d7, d8, 0]]`` (the parameters of
    :func:`latent_pattern`'s Jacobian)."""
    step = torch.zeros_like(H)
    step[:, 0] = delta[:, 0:3]
    step[:, 1] = delta[:, 3:6]
    step[:, 2, :2] = delta[:, 6:8]
    out = H @ (torch.eye(3, dtype=H.dtype, device=H.device) + step)
    return out / out[:, 2:, 2:]


def latent_pattern(H_loc: torch.Tensor, grid: tuple[int, int], num_segments: int, tau: float,
                   supersample: int, dtype: torch.dtype, with_jac: bool
                   ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``S(H)`` on a pixel grid ``(b, Hl, Wl)`` and, optionally, ``dS / d delta (b, 8, Hl, Wl)``.

    Args:
        H_loc: ``(b, 3, 3)`` float64 homographies, block coordinates -> grid px (the grid's
            top-left pixel centre at ``(0, 0)``).
        grid: ``(Hl, Wl)`` the grid's size (px).
        num_segments: star segments ``N``.
        tau: soft-edge width (px).
        supersample: sub-pixel samples per side; ``S`` is their mean.
        dtype: the grid's dtype.
        with_jac: also the derivative; ``delta`` parameterises the block-side update
            ``H <- H (I + Delta)`` (:func:`update_homography`).
    """
    offs = [(o + 0.5) / supersample - 0.5 for o in range(supersample)]
    samples = [_latent_at(H_loc, grid, num_segments, tau, dtype, with_jac, ox, oy)
               for oy in offs for ox in offs]
    if supersample == 1:
        return samples[0]
    S = torch.stack([smp[0] for smp in samples]).mean(dim=0)
    dS = torch.stack([d for _, d in samples if d is not None]).mean(dim=0) if with_jac else None
    return S, dS


def _latent_at(H_loc: torch.Tensor, grid: tuple[int, int], num_segments: int, tau: float, dtype: torch.dtype,
               with_jac: bool, ox: float, oy: float) -> tuple[torch.Tensor, torch.Tensor | None]:
    """:func:`latent_pattern` sampled at the pixel centres moved by ``(ox, oy)`` px."""
    M = torch.linalg.inv(H_loc).to(dtype)
    dev = M.device
    j = torch.arange(grid[1], device=dev, dtype=dtype)[None, None, :] + ox
    i = torch.arange(grid[0], device=dev, dtype=dtype)[None, :, None] + oy

    def row(k: int) -> torch.Tensor:  # one full-grid add: the column and row terms broadcast
        return cast(torch.Tensor,
                    (M[:, k, 0, None, None] * j + M[:, k, 2, None, None]) + M[:, k, 1, None, None] * i)

    inv_w = 1.0 / row(2).clamp_min(1e-6)  # w > 0 in front of the camera (H[2, 2] = 1)
    qx, qy = row(0) * inv_w, row(1) * inv_w
    dist, nx, ny = star_signed_distance_normal(qx, qy, num_segments)  # unit normal of the nearest edge
    # |grad_x dist| = |J^T n| with J = dq/dx = (M[:2, :2] - q M[2, :2]) / w
    nq = nx * qx + ny * qy
    jx = nx * M[:, 0, 0, None, None] + ny * M[:, 1, 0, None, None] - nq * M[:, 2, 0, None, None]
    jy = nx * M[:, 0, 1, None, None] + ny * M[:, 1, 1, None, None] - nq * M[:, 2, 1, None, None]
    jj = jx * jx + jy * jy
    scale = (torch.sqrt(jj) * inv_w).clamp_min(1e-9) * tau
    S = torch.sigmoid(dist / scale)
    if not with_jac:
        return S, None
    # dq/d delta at delta = 0: -(Delta q~)_xy + q (Delta q~)_w with q~ = (q_x, q_y, 1); dS/dq = g n
    # at a fixed normaliser. The normaliser |J^T n| (J = dq/dx) changes too: the update maps q by
    # I - A with A = Delta_2x2 - (Delta q~)_w I - q Delta_w, so |J^T n| changes by -|J^T n| n^T A p,
    # p = J J^T n / |J^T n|^2 (w cancels; n^T p = 1), and S by h n^T A p with h = g dist
    g = S * (1.0 - S) / scale
    h = g * dist
    c = jx * M[:, 2, 0, None, None] + jy * M[:, 2, 1, None, None]
    inv_jj = 1.0 / jj.clamp_min(1e-30)
    px = (jx * M[:, 0, 0, None, None] + jy * M[:, 0, 1, None, None] - qx * c) * inv_jj
    py = (jx * M[:, 1, 0, None, None] + jy * M[:, 1, 1, None, None] - qy * c) * inv_jj
    a = h * px - g * qx  # dS = n_x a d1 + n_x b d2 + n_y a d4 + n_y b d5 + ...
    b = h * py - g * qy
    dS = torch.empty((H_loc.shape[0], 8, *S.shape[1:]), dtype=S.dtype, device=dev)
    torch.mul(nx, a, out=dS[:, 0])
    torch.mul(nx, b, out=dS[:, 1])
    torch.mul(g, nx, out=dS[:, 2]).neg_()
    torch.mul(ny, a, out=dS[:, 3])
    torch.mul(ny, b, out=dS[:, 4])
    torch.mul(g, ny, out=dS[:, 5]).neg_()
    torch.mul(nq, a, out=dS[:, 6]).addcmul_(h, qx).neg_()
    torch.mul(nq, b, out=dS[:, 7]).addcmul_(h, qy).neg_()
    return S, dS
