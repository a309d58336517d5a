"""One star of the target: its colours (the paper's ``eq:hard``) and the signed distance to its
nearest edge.

A star of ``N`` segments sits on every grid corner of the target
(:class:`blurcalib.target.pattern.StarPattern`). Around its centre, the angle
``theta = atan2(u, v)`` (from the +y axis, which points down the page, turning towards +x) splits
into ``N`` sectors ``s = floor(N theta / 2 pi)``; odd sectors are white (1), even ones black (0).
Its edges are the sector rays and the square's border, where the neighbouring star has the
opposite colour. Distances are in block coordinates ``q`` (half a square is 1; the star centre
at 0, the square's corners at ``(+-1, +-1)``).
"""

from __future__ import annotations

import math
from typing import cast

import numpy as np
import torch


def star_sector_white(u: np.ndarray, v: np.ndarray, num_segments: int) -> np.ndarray:
    """Hard star pattern (``eq:hard``): True where the star around the origin is white.

    Args:
        u, v: offsets from the star centre (any unit, x right, y down), same shape.
        num_segments: N, a multiple of 4.
    Returns:
        Boolean array: sector ``floor(N theta / 2 pi)`` odd, ``theta = atan2(u, v) mod 2 pi``.
    """
    theta = np.mod(np.arctan2(u, v), 2.0 * np.pi)
    sector = np.floor(theta * (num_segments / (2.0 * np.pi))).astype(np.int64) % num_segments
    return cast(np.ndarray, (sector % 2) == 1)


def star_signed_distance(q: torch.Tensor, num_segments: int) -> torch.Tensor:
    """Signed distance (block units) from block point ``q`` to the nearest edge of the pattern.

    Edges are the star's sector rays and the square's border (neighbouring stars have the
    opposite colour there). Positive in white, negative in black. Differentiable in ``q``
    almost everywhere. The cell centre is found by rounding ``q / 2``, so ``q`` may lie in a
    neighbouring block.

    Args:
        q: ``(..., 2)`` block coordinates.
        num_segments: N.
    Returns:
        ``(...)`` signed distance, in block units (half a square is 1).
    """
    centre = (2.0 * torch.round(q / 2.0)).detach()
    d = q - centre
    u, v = d[..., 0], d[..., 1]
    sector_width = 2.0 * math.pi / num_segments
    theta = torch.remainder(torch.atan2(u, v), 2.0 * math.pi)
    sector = torch.floor(theta / sector_width).detach()
    white = torch.remainder(sector, 2.0) == 1.0
    dist = torch.full_like(u, float("inf"))
    for k in (sector, sector + 1.0):
        alpha = k * sector_width
        ex, ey = torch.sin(alpha), torch.cos(alpha)  # ray direction in (u, v)
        along = u * ex + v * ey
        perp = torch.abs(u * ey - v * ex)
        ray = torch.where(along > 0, perp, torch.sqrt(u * u + v * v + 1e-30))
        dist = torch.minimum(dist, ray)
    border = 1.0 - torch.maximum(torch.abs(u), torch.abs(v))
    dist = torch.minimum(dist, border)
    return torch.where(white, dist, -dist)


def star_signed_distance_normal(qx: torch.Tensor, qy: torch.Tensor, num_segments: int
                                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`star_signed_distance` and its gradient in ``q``, in closed form (no autograd).

    The nearest sector ray is the one at the nearest multiple of the sector angle (with
    ``N >= 4`` it lies ahead of the point, so the distance is to its line). The gradient of the
    distance to the nearest edge is that edge's unit normal: across a ray
    ``sign(u e_y - v e_x) (e_y, -e_x)``, across the square's border ``-sign`` of the larger
    coordinate; it points into white.

    Args:
        qx, qy: block coordinates, any common shape ``(...)`` (separate contiguous tensors: the
            latent pattern's hot path).
        num_segments: N (a multiple of 4).
    Returns:
        ``(dist, normal_x, normal_y)``, each ``(...)``, block units.
    """
    u = qx - 2.0 * torch.round(qx / 2.0)
    v = qy - 2.0 * torch.round(qy / 2.0)
    t = torch.atan2(u, v) * (num_segments / (2.0 * math.pi))  # angle in sectors
    sector = torch.floor(t)
    sign = 4.0 * (sector * 0.5 - torch.floor(sector * 0.5)) - 1.0  # +1 in white (odd) sectors
    alpha = torch.round(t) * (2.0 * math.pi / num_segments)
    ex, ey = torch.sin(alpha), torch.cos(alpha)
    cross = u * ey - v * ex
    ray = torch.abs(cross)
    side = torch.sign(cross)
    au, av = torch.abs(u), torch.abs(v)
    border = 1.0 - torch.maximum(au, av)
    # 0/1 selectors by arithmetic (faster than comparisons on the CPU): the border is nearer,
    # and |u| >= |v|
    closer = torch.clamp_min(torch.sign(ray - border), 0.0)
    wider = 1.0 - torch.clamp_min(torch.sign(av - au), 0.0)
    ray_x, ray_y = side * ey, -side * ex
    nu = ray_x + closer * (-torch.sign(u) * wider - ray_x)
    nv = ray_y + closer * (torch.sign(v) * (wider - 1.0) - ray_y)
    dist = torch.minimum(ray, border)
    return dist * sign, nu * sign, nv * sign
