"""Local alignment: one translation per block so that neighbouring blocks agree on their corners.

The paper's *Local Alignment*: each block's homography gets a translation,
``H~ = T(x_L) H``, and for every pair of 4-neighbours the two blocks' images of their shared
square corners should coincide::

    argmin_x  sum_{i,j,m} d[H~_{i,j}(1, m), H~_{i,j+1}(-1, m)]^2
                        + d[H~_{i,j}(m, 1), H~_{i+1,j}(m, -1)]^2,   m in {-1, 1}

Since ``T(x) H (q) = H(q) + x``, every residual is linear in the translations:
``x_a - x_b + (H_a(c_a) - H_b(c_b))``. The problem is a sparse linear least-squares problem on
a graph; its gauge (a common translation of a connected set of blocks) is fixed by requiring the
translations of each connected component to sum to zero, which keeps the component's mean
PSF-centroid convention (the blocks were re-centred on their PSF centroids before).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components

from blurcalib.geometry.homography import apply_homography, translation

_CORNERS_RIGHT = (np.array([[1.0, -1.0], [1.0, 1.0]]), np.array([[-1.0, -1.0], [-1.0, 1.0]]))
_CORNERS_DOWN = (np.array([[-1.0, 1.0], [1.0, 1.0]]), np.array([[-1.0, -1.0], [1.0, -1.0]]))


@dataclass(frozen=True)
class LocalAlignment:
    """Result of :func:`align_locally`.

    Attributes:
        translation: ``(B, 2)`` px, ``x_L`` per block (zero for blocks without neighbours).
        H: ``(B, 3, 3)`` aligned homographies ``T(x_L) H``.
        rms_before, rms_after: px, RMS distance between shared corners before and after.
        num_pairs: number of neighbour pairs used.
        component: ``(B,)`` int, connected component of each block.
    """

    translation: np.ndarray
    H: np.ndarray
    rms_before: float
    rms_after: float
    num_pairs: int
    component: np.ndarray


def neighbour_pairs(fx: np.ndarray, fy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of blocks that are 4-neighbours.

    Returns:
        ``(a, b, kind)``: indices into ``fx, fy`` with ``b`` to the right of ``a`` (kind 0) or
        below it (kind 1).
    """
    index = {(int(x), int(y)): i for i, (x, y) in enumerate(zip(fx, fy, strict=True))}
    a, b, kind = [], [], []
    for (x, y), i in index.items():
        for k, (dx, dy) in enumerate(((1, 0), (0, 1))):
            j = index.get((x + dx, y + dy))
            if j is not None:
                a.append(i)
                b.append(j)
                kind.append(k)
    return (np.array(a, dtype=np.int64), np.array(b, dtype=np.int64),
            np.array(kind, dtype=np.int64))


def corner_gaps(H: np.ndarray, a: np.ndarray, b: np.ndarray, kind: np.ndarray) -> np.ndarray:
    """``(P, 2, 2)`` px: ``H_a(c_a) - H_b(c_b)`` for both shared corners of each pair."""
    ca = np.where(kind[:, None, None] == 0, _CORNERS_RIGHT[0], _CORNERS_DOWN[0])
    cb = np.where(kind[:, None, None] == 0, _CORNERS_RIGHT[1], _CORNERS_DOWN[1])
    return cast(np.ndarray, apply_homography(H[a], ca) - apply_homography(H[b], cb))


def align_locally(H: np.ndarray, fx: np.ndarray, fy: np.ndarray,
                  weight: np.ndarray | None = None) -> LocalAlignment:
    """Solve the local-alignment translations of a frame's blocks.

    Args:
        H: ``(B, 3, 3)`` block homographies (block coordinates -> px), after PSF re-centring.
        fx, fy: ``(B,)`` integer feature coordinates of the blocks.
        weight: optional ``(B,)`` confidence per block; a pair weighs the smaller of its two.
    Returns:
        The translations, the aligned homographies and the corner disagreement before/after.
    """
    H = np.asarray(H, dtype=np.float64)
    n = len(H)
    a, b, kind = neighbour_pairs(fx, fy)
    if n == 0 or len(a) == 0:
        return LocalAlignment(np.zeros((n, 2)), H.copy(), 0.0, 0.0, 0, np.arange(n))
    gaps = corner_gaps(H, a, b, kind)  # (P, 2 corners, 2 coords)
    w = np.ones(len(a)) if weight is None else np.minimum(weight[a], weight[b])
    sw = np.sqrt(np.repeat(w, 2))
    # Residual rows per pair and corner: x_a - x_b + gap, separately for x and y.
    rows = np.arange(2 * len(a))
    pa = np.repeat(a, 2)
    pb = np.repeat(b, 2)
    D = sp.csr_matrix((np.concatenate([sw, -sw]), (np.concatenate([rows, rows]),
                                                     np.concatenate([pa, pb]))),
                      shape=(2 * len(a), n))
    adjacency = sp.csr_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    ncomp, comp = connected_components(adjacency, directed=False)
    # Gauge: each component's translations sum to zero (one extra row per component).
    G = sp.csr_matrix((np.ones(n), (comp, np.arange(n))), shape=(ncomp, n))
    A = sp.vstack([D, G]).tocsr()
    x = np.zeros((n, 2))
    for axis in range(2):
        rhs = np.concatenate([-sw * gaps[:, :, axis].ravel(), np.zeros(ncomp)])
        x[:, axis] = spla.lsqr(A, rhs, atol=1e-12, btol=1e-12, iter_lim=10 * n + 100)[0]
    aligned = translation(x) @ H
    after = corner_gaps(aligned, a, b, kind)
    return LocalAlignment(
        x, aligned,
        rms_before=float(np.sqrt(np.mean(np.sum(gaps**2, axis=-1)))),
        rms_after=float(np.sqrt(np.mean(np.sum(after**2, axis=-1)))),
        num_pairs=len(a), component=comp)


def shared_corners(H: np.ndarray, fx: np.ndarray, fy: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Square corners seen by at least two blocks, averaged over the blocks that see them.

    Args:
        H: ``(B, 3, 3)`` block homographies (typically after local alignment).
        fx, fy: ``(B,)`` feature coordinates.
    Returns:
        ``(corner2 (C, 2) int, xy (C, 2) px, count (C,))``: each corner's feature coordinates
        doubled (so the corner at ``(fx + 1/2, fy - 1/2)`` is ``(2 fx + 1, 2 fy - 1)``), its
        mean image position and the number of blocks that see it.
    """
    offsets = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    pts = apply_homography(np.asarray(H, dtype=np.float64), np.broadcast_to(offsets, (len(H), 4, 2)))
    keys = (2 * np.stack([fx, fy], axis=1)[:, None, :] + offsets[None].astype(np.int64)).reshape(-1, 2)
    uniq, inverse, count = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(uniq), 2))
    np.add.at(sums, inverse.ravel(), pts.reshape(-1, 2))
    keep = count >= 2
    return uniq[keep], sums[keep] / count[keep, None], count[keep]
