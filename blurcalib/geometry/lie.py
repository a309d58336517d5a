"""Rotations in torch for the solvers: the cross-product matrix, the SO(3) exponential and the
nearest rotation. One home for what the bundle adjustment, the frame fit and the uncertainty
propagation share (rotation increments ``R <- exp([omega]_x) R``)."""

from __future__ import annotations

from typing import cast

import numpy as np
import numpy.typing as npt
import torch

__all__ = ["exp_so3", "orthonormal", "skew"]


def skew(v: torch.Tensor) -> torch.Tensor:
    """``[v]_x (N, 3, 3)`` of ``v (N, 3)``: ``[v]_x u = v x u``."""
    z = torch.zeros_like(v[:, 0])
    return torch.stack([torch.stack([z, -v[:, 2], v[:, 1]], -1),
                        torch.stack([v[:, 2], z, -v[:, 0]], -1),
                        torch.stack([-v[:, 1], v[:, 0], z], -1)], -2)


def exp_so3(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``(N, 3, 3)`` of rotation vectors ``w (N, 3)`` (rad; Rodrigues)."""
    theta = w.norm(dim=-1, keepdim=True).clamp_min(1e-300)[..., None]
    K = skew(w / theta[..., 0])
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(K)
    return eye + torch.sin(theta) * K + (1 - torch.cos(theta)) * (K @ K)


def orthonormal(R: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The nearest rotation (SVD) to a numerically drifted one ``(3, 3)``."""
    U, _, Vt = np.linalg.svd(R)
    return cast(npt.NDArray[np.float64], U @ Vt)
