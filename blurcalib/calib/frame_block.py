"""The per-frame block of the generic bundle adjustment (:mod:`blurcalib.calib.bundle`): a
frame's pose and image shift, and, for a rolling shutter, its rolling parameters; the camera points
they give and their Jacobians.

A frame's block holds ``omega (3), dt (3), s (2)`` (``R <- exp([omega]_x) R``, ``t <- t + dt``,
image shift ``s`` px) and, with rolling rows, ``theta = (a_w, a_v, b_w, b_v)`` (12 values: rad, m,
rad, m): an observation on row ``y`` (share of the readout, ``y = (v - (H - 1) / 2) / H``) sees::

    X = exp([y a_w + y^2 b_w]_x) (R P + t) + y a_v + y^2 b_v      (m, camera frame)

(``docs/rolling-shutter.md``). Tensors are torch float64.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from blurcalib.geometry.lie import exp_so3, skew

__all__ = [
    "RollingRows",
    "checked_rolling_rows",
    "frame_jacobian",
    "rolling_frame_jacobian",
    "rolling_points",
    "rolling_prior_weights",
]


@dataclass(frozen=True)
class RollingRows:
    """The rolling-shutter rows of :func:`blurcalib.calib.bundle.bundle_adjust` (module docstring).

    Attributes:
        row: ``(N,)`` each observation's row as a share of the readout, ``y = (v - (H - 1) / 2) / H``.
        moving: ``(F,)`` bool, the frames with rolling parameters.
        twist_sigma: the rolling parameters' prior, rad and times the frame's distance m.
    """

    row: np.ndarray = field(repr=False)
    moving: np.ndarray
    twist_sigma: float = 3.0


def rolling_points(R: torch.Tensor, t: torch.Tensor, theta: torch.Tensor, fr: torch.Tensor,
                   P: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Camera points of the rolling model ``X (N, 3)`` m (module docstring), their rotation
    ``exp([y a_w + y^2 b_w]_x) (N, 3, 3)`` and ``R P (N, 3)``, from ``R (F, 3, 3)``, ``t (F, 3)``,
    ``theta (F, 12)``, ``fr (N,)``, ``P (N, 3)`` and ``y (N,)``."""
    RP = torch.einsum("nij,nj->ni", R[fr], P)
    X0 = RP + t[fr]
    th = theta[fr]
    w = y[:, None] * th[:, 0:3] + (y * y)[:, None] * th[:, 6:9]
    v = y[:, None] * th[:, 3:6] + (y * y)[:, None] * th[:, 9:12]
    Ri = exp_so3(w)
    return torch.einsum("nij,nj->ni", Ri, X0) + v, Ri, RP


def rolling_prior_weights(t: torch.Tensor, twist_sigma: float) -> torch.Tensor:
    """``(F, 12)`` weights ``1 / sigma^2`` of the rolling parameters' zero-mean prior: ``sigma``
    is ``twist_sigma`` rad for ``a_w, b_w`` and ``twist_sigma |t_f|`` m for ``a_v, b_v``, from the
    frames' translations ``t (F, 3)`` m."""
    sig = torch.full_like(t, twist_sigma)
    sig_v = twist_sigma * t.norm(dim=1, keepdim=True).expand(-1, 3)
    return 1.0 / torch.cat([sig, sig_v, sig, sig_v], dim=1) ** 2


def rolling_frame_jacobian(J_p: torch.Tensor, Ri: torch.Tensor, RP: torch.Tensor, X: torch.Tensor,
                           y: torch.Tensor) -> torch.Tensor:
    """``(N, 2, 20)`` derivatives of the rolling projections in their frames' block, columns
    ``omega, dt, s, a_w, a_v, b_w, b_v`` (the rotation increments to first order), from
    ``J_p = du/dX (N, 2, 3)`` at the rolling points ``X (N, 3)``, their rotation ``Ri (N, 3, 3)``,
    ``R P (N, 3)`` and the rows ``y (N,)``."""
    twist = torch.cat([-J_p @ skew(X), J_p], dim=2)
    ys = y[:, None, None]
    return torch.cat([frame_jacobian(J_p @ Ri, RP), ys * twist, ys * ys * twist], dim=2)


def frame_jacobian(J_p: torch.Tensor, RX: torch.Tensor) -> torch.Tensor:
    """``(N, 2, 8)`` derivatives of the projections in their frames' block, columns ``omega (3),
    dt (3), s (2)`` (``R <- exp([omega]_x) R``, ``t <- t + dt``, shift ``s``), from ``J_p = du/dX
    (N, 2, 3)`` and the rotated target points ``RX = R P (N, 3)`` (m)."""
    eye2 = torch.eye(2, dtype=J_p.dtype, device=J_p.device).expand(len(J_p), 2, 2)
    return torch.cat([-J_p @ skew(RX), J_p, eye2], dim=2)


def checked_rolling_rows(rolling: RollingRows | None, n: int, F: int) -> RollingRows | None:
    """``rolling`` with arrays of the right shapes; ValueError names what is wrong."""
    if rolling is None:
        return None
    row = np.asarray(rolling.row, dtype=np.float64).reshape(-1)
    moving = np.asarray(rolling.moving, dtype=bool).reshape(-1)
    if row.shape != (n,) or moving.shape != (F,) or not np.all(np.isfinite(row)):
        raise ValueError(f"rolling rows must be finite of shape ({n},) and moving frames of shape ({F},); "
                         f"got {row.shape} and {moving.shape}")
    if not rolling.twist_sigma > 0:
        raise ValueError(f"rolling twist_sigma must be > 0, got {rolling.twist_sigma}")
    return RollingRows(row, moving, rolling.twist_sigma)
