"""Plane homographies: the target-plane homography (``eq:T``), translations and their action on points.

Homographies are ``(..., 3, 3)`` float64 arrays mapping homogeneous 2-D points; pixels follow
OpenCV (the centre of the top-left pixel is ``(0, 0)`` px).
"""

from __future__ import annotations

from typing import cast

import numpy as np
import numpy.typing as npt
from numpy.typing import ArrayLike

from blurcalib.geometry.pose import Pose, as_points


def _homography_xy(H: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply ``H (..., 3, 3)`` to ``pts (..., N, 2)``; returns the two output components."""
    x = pts[..., 0]
    y = pts[..., 1]
    h = H[..., None, :, :]
    w = h[..., 2, 0] * x + h[..., 2, 1] * y + h[..., 2, 2]
    u = (h[..., 0, 0] * x + h[..., 0, 1] * y + h[..., 0, 2]) / w
    v = (h[..., 1, 0] * x + h[..., 1, 1] * y + h[..., 1, 2]) / w
    return u, v



def plane_homography(K: ArrayLike, pose: Pose) -> np.ndarray:
    """Target-plane homography ``H = K [r1 r2 t]`` (eq:T), shape (3, 3).

    Maps target-plane metres ``(X, Y, 1)`` to undistorted pixel coordinates (px).
    """
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must have shape (3, 3), got {K.shape}")
    return cast(npt.NDArray[np.float64], K @ np.column_stack([pose.R[:, 0], pose.R[:, 1], pose.t]))


def translation(x: ArrayLike) -> np.ndarray:
    """The paper's 2-D translation ``T(x)``: ``(..., 2)`` px -> ``(..., 3, 3)`` homographies."""
    x = np.asarray(x, dtype=np.float64)
    T = np.broadcast_to(np.eye(3), (*x.shape[:-1], 3, 3)).copy()
    T[..., :2, 2] = x
    return T


def apply_homography(H: ArrayLike, pts: ArrayLike) -> np.ndarray:
    """Apply homographies to 2-D points (with perspective division).

    Args:
        H: ``(3, 3)`` or ``(B, 3, 3)``.
        pts: ``(N, 2)`` or ``(B, N, 2)``; batch dimensions broadcast against ``H``'s.

    Returns:
        ``(N, 2)`` or ``(B, N, 2)``; points mapped to infinity give inf/nan.
    """
    H = np.asarray(H, dtype=np.float64)
    if H.ndim < 2 or H.shape[-2:] != (3, 3):
        raise ValueError(f"H must have shape (..., 3, 3), got {H.shape}")
    pts = as_points(pts, 2, "pts")
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = _homography_xy(H, pts)
    return np.stack([u, v], axis=-1)


def homography_centre(H: ArrayLike) -> np.ndarray:
    """``H(0, 0)``: where homographies ``(..., 3, 3)`` map the origin, ``(..., 2)`` =
    ``H[:2, 2] / H[2, 2]``; for a block homography, its star centre (px). NaN (both
    coordinates) where ``H`` is degenerate (maps the origin to infinity or is not finite)."""
    H = np.asarray(H, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        centre: npt.NDArray[np.float64] = H[..., :2, 2] / H[..., 2:, 2]
    centre[~np.isfinite(centre).all(axis=-1)] = np.nan
    return centre


def homography_scale(H: ArrayLike) -> np.ndarray:
    """Local scale of homographies ``(..., 3, 3)`` at the origin, ``(...)``: ``sqrt(|det J|)``
    with ``J = (H[:2, :2] - H(0, 0) H[2, :2]) / H[2, 2]`` the Jacobian of the mapping there (px
    per unit of the source plane; a block homography's square, 2 units wide, is twice this in
    px). NaN where ``H`` is degenerate."""
    H = np.asarray(H, dtype=np.float64)
    c = homography_centre(H)
    with np.errstate(divide="ignore", invalid="ignore"):
        J: npt.NDArray[np.float64] = (H[..., :2, :2] - c[..., :, None] * H[..., None, 2, :2]) / H[..., 2:, 2:]
        return np.sqrt(np.abs(J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]))


