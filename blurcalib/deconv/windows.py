"""The observed window of each block and whether it can be fitted."""

from __future__ import annotations

import numpy as np

from blurcalib.deconv.settings import DeconvSettings
from blurcalib.io.results import BlockStatus


def block_windows(H0: np.ndarray, image_shape: tuple[int, int], s: DeconvSettings
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[BlockStatus]]:
    """Windows of the blocks and which can be fitted (:func:`blurcalib.deconv.blocks.fit_blocks`'s rules).

    Args:
        H0: ``(B, 3, 3)`` block homographies; image_shape: ``(height, width)``; s: the settings
            (loss extent, window margin, size limits).
    Returns:
        ``origin (B, 2)`` int ``(x0, y0)``, ``size (B, 2)`` int ``(w, h)`` of the observed
        window (bounding box of ``H([-e, e]^2)``, ``e`` the loss extent, plus the margin), the
        normalised ``H (B, 3, 3)`` and a status per block (``accepted`` for those to fit).
    """
    height, width = image_shape
    e = s.loss_extent
    corners = np.array([[-e, -e, 1], [e, -e, 1], [e, e, 1], [-e, e, 1]], dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        finite = np.all(np.isfinite(H0), axis=(1, 2))
        h = np.where(finite[:, None, None], H0, 0.0)
        ok = finite & (np.abs(h[:, 2, 2]) >= 1e-12 * np.maximum(np.abs(h).max(axis=(1, 2)), 1e-300))
        H = np.where(ok[:, None, None], h / np.where(ok, h[:, 2, 2], 1.0)[:, None, None], H0)
        xs = np.einsum("cj,bij->bci", corners, np.where(ok[:, None, None], H, np.eye(3)))  # (B, 4, 3)
        ok &= np.all(xs[..., 2] > 1e-9, axis=1)
        pts = xs[..., :2] / np.where(ok[:, None], xs[..., 2], 1.0)[..., None]
        edges = np.roll(pts, -1, axis=1) - pts
        nxt = np.roll(edges, -1, axis=1)
        cross = edges[..., 0] * nxt[..., 1] - edges[..., 1] * nxt[..., 0]
        area = 0.5 * np.abs(np.sum(pts[..., 0] * np.roll(pts[..., 1], -1, axis=1)
                                   - np.roll(pts[..., 0], -1, axis=1) * pts[..., 1], axis=1))
        ok &= (np.all(cross > 0, axis=1) | np.all(cross < 0, axis=1)) & (np.sqrt(area) / e >= s.min_square_px)
        lo = np.where(ok[:, None], np.floor(pts.min(axis=1)), 0).astype(np.int64) - s.window_margin
        hi = np.where(ok[:, None], np.ceil(pts.max(axis=1)), 0).astype(np.int64) + s.window_margin
    ok &= np.all(hi - lo + 1 <= s.max_window_px, axis=1)
    origin = np.where(ok[:, None], lo, 0)
    size = np.where(ok[:, None], hi - lo + 1, 0)
    outside = (lo[:, 0] < 0) | (lo[:, 1] < 0) | (hi[:, 0] > width - 1) | (hi[:, 1] > height - 1)
    status = [BlockStatus.DEGENERATE_HOMOGRAPHY if not good else
              BlockStatus.OUTSIDE_IMAGE if out else BlockStatus.ACCEPTED
              for good, out in zip(ok.tolist(), outside.tolist(), strict=True)]
    return origin, size, H, status
