"""The bias of a block homography's star centre under lens distortion, and its correction.

A block is fitted with a homography ``H`` (block coordinates ``q in [-1, 1]^2`` -> px), the
paper's local model. Through a distorting lens the star's image is not a homography of the
pattern but ``W(q) = pi(R^T U q)``: the pattern plane maps to the viewing directions by a
homography ``U`` (any central camera: the plane seen from the projection centre, expressed on a
plane facing the block), then the camera's projection ``pi`` (any model of the parametric
family, :mod:`blurcalib.camera.lens`; a ray may be 90 degrees off the axis and more). The
fitted ``H`` is the homography nearest to ``W`` over the square, and its centre ``H(0)`` misses
``W(0)`` by a bias that grows with the projection's curvature: on simulated sharp frames through
the D435I-like lens (``synth.d435i_like_camera``) star centres sit ~0.002 px outwards near the
image centre and 0.006-0.008 px inwards beyond 450 px from it, with no such trend when the lens
has no distortion; through a 130 degree Kannala-Brandt fisheye (``sim.truth.fisheye_camera``)
it reaches a few tenths of a pixel (``docs/generic.md``). The bias is systematic, as large as or
larger than the features' noise, and shortens the calibrated focal length.

Given a camera (the sharp-set parametric calibration), the bias is predicted block by block::

    v(q) = pi^-1(H q)                                (unit rays, (M, 3))
    R: R v(0) = (0, 0, 1)                            (the block's facing frame)
    m(q) = [R v(q)]~                                 (rays on the facing plane z = 1)
    U = argmin sum_q |U q - m(q)|^2                  (the plane's homography)
    W(q) = pi(R^T (U q, 1))
    G = argmin sum_q |G q - W(q)|^2                  (the homography a fit finds)
    bias = G(0) - W(0)                               (px)

over a 15 x 15 lattice of ``q`` on the area the block was fitted over (its square, or
``|q|_inf <= e`` for a block fitted with a loss extent ``e``, :attr:`BlockTable.loss_extent`: the
bias grows about as ``e^2``), by least squares in the homography's entries with ``h33 = 1``.
For a perspective lens near the axis the facing plane is close to the normalised image plane
(``R ~ I``). Subtracting the bias removes the trend (median radial error within 0.0006 px at
every radius on the D435I-like frames above, median error 0.0060 -> 0.0049 px,
``docs/generic.md``).

Pixel convention: OpenCV (the centre of the top-left pixel is ``(0, 0)``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import cast

import numpy as np

from blurcalib.camera.lens import ParametricCamera
from blurcalib.camera.parametric import BrownConrady
from blurcalib.geometry.homography import apply_homography, translation
from blurcalib.io.results import BlockTable, FeatureFlags, FeatureTable

__all__ = ["centre_bias", "correct_blocks", "correct_features", "facing_rotations", "fit_homographies"]

_STEPS = np.linspace(-1.0, 1.0, 15)
_LATTICE = np.stack(np.meshgrid(_STEPS, _STEPS), axis=-1).reshape(-1, 2)
"""``(225, 2)`` block coordinates of the fits; the middle row is ``q = 0``."""
_CENTRE = len(_LATTICE) // 2


def fit_homographies(q: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least-squares homographies ``G (N, 3, 3)`` with ``G q ~ y``, ``G[2, 2] = 1``.

    Linear least squares in the 8 entries (the DLT residual ``G_12 q - (G_3 q) y``), each set
    of targets ``y (N, M, 2)`` first moved to its sample at ``q = 0`` (``q (M, 2)`` must hold it
    at row ``M // 2``) and scaled to unit size, then the normal equations solved as one batch.
    """
    N, M, _ = y.shape
    origin = y[:, M // 2, None, :]
    scale = np.maximum(np.abs(y - origin).max(axis=(1, 2), keepdims=True), 1e-12)
    Y = (y - origin) / scale
    qx, qy = q[:, 0], q[:, 1]
    A = np.zeros((N, 2 * M, 8))
    A[:, :M, 0], A[:, :M, 1], A[:, :M, 2] = qx, qy, 1.0
    A[:, M:, 3], A[:, M:, 4], A[:, M:, 5] = qx, qy, 1.0
    A[:, :M, 6], A[:, :M, 7] = -qx * Y[..., 0], -qy * Y[..., 0]
    A[:, M:, 6], A[:, M:, 7] = -qx * Y[..., 1], -qy * Y[..., 1]
    b = np.concatenate([Y[..., 0], Y[..., 1]], axis=1)[..., None]
    At = A.transpose(0, 2, 1)
    h = np.linalg.solve(At @ A, At @ b)[..., 0]
    G = np.concatenate([h, np.ones((N, 1))], axis=1).reshape(N, 3, 3)
    back = np.zeros((N, 3, 3))
    back[:, 0, 0] = back[:, 1, 1] = scale[:, 0, 0]
    back[:, :2, 2] = origin[:, 0]
    back[:, 2, 2] = 1.0
    return cast(np.ndarray, back @ G)


_CHUNK = 512
"""Blocks per batch of :func:`centre_bias` (its least-squares systems take ~15 kB per block)."""


def facing_rotations(rays: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` rotations ``R`` with ``R v = (0, 0, 1)`` for unit rays ``v (N, 3)``: the
    frame of a virtual pinhole looking along each ray (the shortest turn; about the x axis for a
    ray pointing backwards). NaN rows give NaN rotations."""
    v = np.asarray(rays, dtype=np.float64).reshape(-1, 3)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(v, z)
    s = np.linalg.norm(axis, axis=1)
    c = v[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where((s > 1e-12)[:, None], axis / np.where(s > 1e-12, s, 1.0)[:, None],
                     np.array([1.0, 0.0, 0.0]))
    K = np.zeros((len(v), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    angle = np.arctan2(s, c)
    return cast(np.ndarray, np.eye(3) + np.sin(angle)[:, None, None] * K
                + (1.0 - np.cos(angle))[:, None, None] * (K @ K))


def _rays(camera: BrownConrady | ParametricCamera, px: np.ndarray) -> np.ndarray:
    """Unit viewing directions ``(N, 3)`` of pixels ``(N, 2)``; NaN where a pixel has no ray. A
    :class:`BrownConrady` camera uses its own inverse (normalised coordinates ``(x, y, 1)``)."""
    if isinstance(camera, BrownConrady):
        rays = np.concatenate([camera.unproject(px), np.ones((len(px), 1))], axis=1)
        return cast(np.ndarray, rays / np.linalg.norm(rays, axis=1, keepdims=True))
    return camera.unproject(px)


def centre_bias(camera: BrownConrady | ParametricCamera, H: np.ndarray,
                extent: np.ndarray | float = 1.0) -> np.ndarray:
    """``(N, 2)`` px: the bias ``G(0) - W(0)`` of the star centre of each block homography
    ``H (N, 3, 3)`` fitted over ``|q|_inf <= extent`` (``(N,)`` or a scalar) through ``camera``
    (any model of the parametric family, any angle off the axis; module docstring). NaN for a
    non-finite ``H`` or a block whose pixels have no ray or reach the back of its facing plane."""
    H = np.asarray(H, dtype=np.float64).reshape(-1, 3, 3)
    e = np.broadcast_to(np.asarray(extent, dtype=np.float64), (len(H),))
    H = H * np.stack([e, e, np.ones_like(e)], axis=-1)[:, None, :]  # H S(e): the area is [-1, 1]^2
    out = np.full((len(H), 2), np.nan)
    rows = np.flatnonzero(np.all(np.isfinite(H), axis=(1, 2)))
    for start in range(0, len(rows), _CHUNK):
        sel = rows[start:start + _CHUNK]
        rays = _rays(camera, apply_homography(H[sel], _LATTICE[None]).reshape(-1, 2)).reshape(len(sel), -1, 3)
        R = facing_rotations(rays[:, _CENTRE])
        local = np.einsum("nij,nmj->nmi", R, rays)
        with np.errstate(invalid="ignore", divide="ignore"):
            m = local[..., :2] / local[..., 2:]
            good = np.all(np.isfinite(m), axis=(1, 2)) & np.all(local[..., 2] > 0, axis=1)
        if not good.any():
            continue
        sel, R, m = sel[good], R[good], m[good]
        plane = apply_homography(fit_homographies(_LATTICE, m), _LATTICE[None])
        facing = np.concatenate([plane, np.ones((*plane.shape[:2], 1))], axis=-1)
        W = camera.project(np.einsum("nji,nmj->nmi", R, facing).reshape(-1, 3)).reshape(len(sel), -1, 2)
        G = fit_homographies(_LATTICE, W)
        out[sel] = G[:, :2, 2] / G[:, 2:, 2] - W[:, _CENTRE]
    return out


def correct_blocks(blocks: BlockTable, camera: BrownConrady | ParametricCamera) -> BlockTable:
    """The blocks with each ``H`` moved by minus its :func:`centre_bias` (``H <- T(-bias) H``),
    so that their centres, and the features made from them, are corrected."""
    assert blocks.loss_extent is not None  # filled in by BlockTable
    bias = np.nan_to_num(centre_bias(camera, blocks.H, blocks.loss_extent))
    return replace(blocks, H=translation(-bias) @ blocks.H)


def correct_features(features: FeatureTable, blocks: BlockTable,
                     camera: BrownConrady | ParametricCamera) -> FeatureTable:
    """``features`` moved by minus the :func:`centre_bias` of their blocks (matched on frame and
    feature id) and flagged :attr:`FeatureFlags.LENS_CORRECTED`; features without a block are
    left as they are."""
    row = {(f, int(i)): k for k, (f, i) in enumerate(zip(blocks.frame, blocks.feature_id, strict=True))}
    pairs = zip(features.frame, features.feature_id, strict=True)
    match = np.array([row.get((f, int(i)), -1) for f, i in pairs], dtype=np.int64)
    found = match >= 0
    bias = np.zeros((len(features), 2))
    assert blocks.loss_extent is not None  # filled in by BlockTable
    bias[found] = np.nan_to_num(centre_bias(camera, blocks.H[match[found]], blocks.loss_extent[match[found]]))
    flags = np.where(found, features.flags | int(FeatureFlags.LENS_CORRECTED), features.flags)
    return replace(features, x=features.x - bias[:, 0], y=features.y - bias[:, 1], flags=flags)
