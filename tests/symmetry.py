"""A small, independent star-centre detector for checking rendered frames.

Stars are point-symmetric about their centre (a 180-degree turn maps sector s to s + N/2, which
has the same colour when N is a multiple of 4), so the centre minimises
``sum_d (I(c + d) - I(c - d))^2`` over a disc of offsets ``d``. Solved by Gauss-Newton on a cubic
spline of the image, for all features at once. Under perspective the symmetry is only local, so
this is a check for mildly tilted views, not a product detector.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi


def symmetry_centres(image: np.ndarray, start: np.ndarray, radius: float = 5.0,
                     iterations: int = 10) -> np.ndarray:
    """Refine star centres ``start (N, 2)`` px (OpenCV convention) in ``image (H, W)``."""
    coef = ndi.spline_filter(np.asarray(image, dtype=np.float64), order=3)
    grid = np.arange(-radius, radius + 1e-9, 0.5)
    dx, dy = np.meshgrid(grid, grid)
    r2 = dx**2 + dy**2
    keep = (r2 <= radius**2) & (r2 >= 1.0)
    d = np.stack([dx[keep], dy[keep]], axis=1)

    def sample(pts: np.ndarray) -> np.ndarray:
        return ndi.map_coordinates(coef, [pts[..., 1], pts[..., 0]], order=3, prefilter=False,
                                   mode="nearest")

    h = 0.1
    steps = (np.array([h, 0.0]), np.array([0.0, h]))
    c = np.array(start, dtype=np.float64)
    for _ in range(iterations):
        plus = c[:, None, :] + d[None]
        minus = c[:, None, :] - d[None]
        residual = sample(plus) - sample(minus)
        J = np.stack([(sample(plus + e) - sample(plus - e) - sample(minus + e) + sample(minus - e))
                      / (2 * h) for e in steps], axis=-1)
        A = np.einsum("nmi,nmj->nij", J, J) + 1e-9 * np.eye(2)
        g = np.einsum("nmi,nm->ni", J, residual)
        c -= np.linalg.solve(A, g[..., None])[..., 0]
    return c
