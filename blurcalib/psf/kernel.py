"""Everything about a point-spread function (PSF, kernel): its centroid, its moments, its
boundary energy, its re-centring and the translational ambiguity of deconvolution.

Pixel ``(i, j)`` (row, column) of a ``K x K`` kernel sits at offset ``(j - c, i - c)`` px from
the kernel centre, ``c = (K - 1) / 2`` (``docs/conventions.md``). Kernels are non-negative and
sum to 1 unless stated.
"""

from __future__ import annotations

from typing import NamedTuple, cast, overload

import numpy as np

from blurcalib.geometry.homography import homography_scale, translation

__all__ = [
    "PsfMoments",
    "blur_extent",
    "blur_per_square",
    "boundary_energy",
    "psf_centroid",
    "psf_moments",
    "recentre",
    "resize_kernels",
    "shift_pair",
]


class PsfMoments(NamedTuple):
    """Moment figures of a PSF (or of a batch: each field gains a leading ``B`` axis)."""

    centroid: np.ndarray
    """``(2,)`` or ``(B, 2)`` px, intensity centroid ``(x, y)`` relative to the kernel centre."""
    sigma_major: np.ndarray | float
    """px, square root of the larger eigenvalue of the central second-moment matrix."""
    sigma_minor: np.ndarray | float
    """px, square root of the smaller eigenvalue."""
    eccentricity: np.ndarray | float
    """``sqrt(1 - sigma_minor^2 / sigma_major^2)``; 0 for a delta."""
    orientation: np.ndarray | float
    """rad in ``(-pi/2, pi/2]``, of the major axis, from +x towards +y; 0 for a round PSF."""


def psf_moments(psf: np.ndarray) -> PsfMoments:
    """Centroid and second-moment ellipse of a PSF or a batch of PSFs.

    The kernel is normalised by its sum (which must be non-zero); pixel ``(i, j)`` sits at
    offset ``(j - c, i - c)`` px, ``c = (K - 1) / 2``.

    Args:
        psf: ``(K, K)`` or ``(B, K, K)`` kernel(s), non-negative.
    Returns:
        :class:`PsfMoments`; floats for one kernel, ``(B,)`` arrays (centroid ``(B, 2)``)
        for a batch.
    """
    k = np.asarray(psf, dtype=np.float64)
    single = k.ndim == 2
    if single:
        k = k[None]
    if k.ndim != 3 or k.shape[1] != k.shape[2]:
        raise ValueError(f"psf must be (K, K) or (B, K, K), got {np.shape(psf)}")
    c = (k.shape[1] - 1) / 2.0
    offs = np.arange(k.shape[1], dtype=np.float64) - c
    w = k / k.sum(axis=(1, 2), keepdims=True)
    wx = w.sum(axis=1)  # (B, K): marginal over rows, indexed by column j
    wy = w.sum(axis=2)  # (B, K): marginal over columns, indexed by row i
    mx = wx @ offs
    my = wy @ offs
    cxx = wx @ offs**2 - mx**2
    cyy = wy @ offs**2 - my**2
    cxy = np.einsum("bij,i,j->b", w, offs, offs) - mx * my
    half_trace = 0.5 * (cxx + cyy)
    radius = np.hypot(0.5 * (cxx - cyy), cxy)
    major = np.sqrt(np.maximum(half_trace + radius, 0.0))
    minor = np.sqrt(np.maximum(half_trace - radius, 0.0))
    ratio = np.divide(minor, major, out=np.ones_like(major), where=major > 0)
    ecc = np.sqrt(np.maximum(1.0 - ratio**2, 0.0))
    orient = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
    orient = np.where(orient <= -np.pi / 2, orient + np.pi, orient)
    centroid = np.stack([mx, my], axis=1)
    if single:
        return PsfMoments(centroid[0], float(major[0]), float(minor[0]), float(ecc[0]),
                          float(orient[0]))
    return PsfMoments(centroid, major, minor, ecc, orient)


@overload
def blur_extent(sigma_major: float) -> float: ...


@overload
def blur_extent(sigma_major: np.ndarray) -> np.ndarray: ...


def blur_extent(sigma_major: np.ndarray | float) -> np.ndarray | float:
    """Blur extent (px) of PSFs with major-axis second moment ``sigma_major`` (px): ``sqrt(12)
    sigma_major``, the length of a straight blur with that second moment."""
    return cast("np.ndarray | float", np.sqrt(12.0) * sigma_major)


def blur_per_square(sigma_major: np.ndarray, H: np.ndarray) -> np.ndarray:
    """``(B,)`` blur extent over the star square's side: :func:`blur_extent` over ``2 |det
    J|^(1/2)``, ``J`` the Jacobian of the block homographies ``H (B, 3, 3)`` at the star centre
    (:func:`blurcalib.geometry.homography.homography_scale`); NaN where ``sigma_major`` is."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return blur_extent(np.asarray(sigma_major, dtype=np.float64)) / (2.0 * homography_scale(H))


def boundary_energy(psf: np.ndarray, ring: int = 2) -> np.ndarray | float:
    """Share of a PSF's energy in its outer ``ring``-pixel border (a truncation indicator).

    Args:
        psf: ``(K, K)`` or ``(B, K, K)`` kernel(s) with non-zero sum.
        ring: border width in pixels.
    Returns:
        ``sum(border) / sum(all)``: a float for one kernel, ``(B,)`` for a batch.
    """
    k = np.asarray(psf, dtype=np.float64)
    if k.ndim not in (2, 3) or k.shape[-1] != k.shape[-2]:
        raise ValueError(f"psf must be (K, K) or (B, K, K), got {k.shape}")
    inner = k[..., ring:k.shape[-1] - ring, ring:k.shape[-1] - ring].sum(axis=(-2, -1))
    total = k.sum(axis=(-2, -1))
    share = (total - inner) / total
    return float(share) if k.ndim == 2 else share


def psf_centroid(psf: np.ndarray, threshold: float = 0.0) -> np.ndarray:
    """Intensity-weighted centroid of PSFs, px relative to the kernel centre.

    Values below ``threshold`` times the kernel's peak are ignored (a robust variant for
    kernels with negative ringing or a noise floor; the solver's kernels are non-negative and
    support-restricted, so its default is 0).

    Args:
        psf: ``(K, K)`` or ``(B, K, K)`` kernels (pixel ``(i, j)`` at offset ``(j - c, i - c)``).
        threshold: share of the peak below which values get zero weight (0 keeps all values).
    Returns:
        ``(2,)`` or ``(B, 2)`` float64 ``(x, y)`` px.
    """
    k = np.asarray(psf, dtype=np.float64)
    single = k.ndim == 2
    k = k[None] if single else k
    c = (k.shape[-1] - 1) / 2.0
    peak = k.max(axis=(1, 2), keepdims=True)
    w = np.where(k >= threshold * peak, k, 0.0) if threshold > 0 else k
    total = w.sum(axis=(1, 2))
    offs = np.arange(k.shape[-1], dtype=np.float64) - c
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.stack([w.sum(axis=1) @ offs, w.sum(axis=2) @ offs], axis=1) / total[:, None]
    return cast(np.ndarray, out[0] if single else out)


def resize_kernels(k: np.ndarray, size: int) -> np.ndarray:
    """``(..., K, K)`` kernels zero-padded or cropped (centred) to ``(..., size, size)`` (``K`` and
    ``size`` odd): padding leaves a kernel unchanged as a convolution kernel."""
    p = (size - k.shape[-1]) // 2
    if p >= 0:
        return np.pad(k, [(0, 0)] * (k.ndim - 2) + [(p, p), (p, p)]) if p else k
    return k[..., -p:k.shape[-1] + p, -p:k.shape[-1] + p]


def _shift_kernels(psf: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``k'(d) = k(d + s)`` by separable linear interpolation (zero outside the window).

    Linear interpolation keeps the kernel non-negative, its sum and its centroid (moved by exactly
    ``-s``) up to weight leaving the window; it widens the kernel by a variance of
    ``f (1 - f) <= 1/4`` px^2 per axis (``f`` the fractional part of the shift).

    Args:
        psf: ``(B, K, K)``; shift: ``(B, 2)`` px ``(s_x, s_y)``.
    """
    B, K, _ = psf.shape
    out = psf
    bi = np.arange(B)[:, None, None, None]
    ar = np.arange(K)
    for axis, s in ((2, shift[:, 0]), (1, shift[:, 1])):
        base = np.floor(s)
        frac = s - base
        w = np.stack([1.0 - frac, frac], axis=1)  # (B, 2)
        idx = ar[None, :, None] + base[:, None, None].astype(np.int64) + np.arange(2)  # (B, K, 2)
        valid = (idx >= 0) & (idx < K)
        idx = np.clip(idx, 0, K - 1)
        if axis == 2:
            taps = out[bi, ar[None, :, None, None], idx[:, None, :, :]]  # (B, K, K, 2)
            out = np.sum(taps * (w[:, None, None, :] * valid[:, None]), axis=-1)
        else:
            taps = out[bi, idx[:, :, None, :], ar[None, None, :, None]]
            out = np.sum(taps * (w[:, None, None, :] * valid[:, :, None]), axis=-1)
    return out


def recentre(H: np.ndarray, psf: np.ndarray, threshold: float = 0.0
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PSF re-centring (end of *Local Alignment*): move each kernel's centroid to its centre.

    With ``c`` the kernel centroid (:func:`psf_centroid`), ``k'(d) = k(d + c)`` (sub-pixel, linear
    interpolation; sum and non-negativity kept) and ``H' = T(c) H``. By the translational
    ambiguity ``k' * S(H') = k * S(H)`` the model is unchanged (up to the interpolation), while
    ``H'(0, 0)`` becomes the centre of the star's time-averaged image. A kernel whose centroid is
    undefined (zero sum) is returned unchanged with ``c`` NaN.

    Args:
        H: ``(3, 3)`` or ``(B, 3, 3)`` block homographies (block coords -> px).
        psf: ``(K, K)`` or ``(B, K, K)`` kernels.
        threshold: centroid threshold, share of each kernel's peak.
    Returns:
        ``(H', psf', c)``: float64, shapes as given, ``c`` ``(2,)`` / ``(B, 2)`` px.
    """
    H = np.asarray(H, dtype=np.float64)
    k = np.asarray(psf, dtype=np.float64)
    single = k.ndim == 2
    Hb, kb = (H[None], k[None]) if single else (H, k)
    c = psf_centroid(kb, threshold)
    ok = np.all(np.isfinite(c), axis=1)
    c_safe = np.where(ok[:, None], c, 0.0)
    k_out = _shift_kernels(kb, c_safe)
    sums = kb.sum(axis=(1, 2), keepdims=True)
    out_sums = k_out.sum(axis=(1, 2), keepdims=True)
    scale = np.divide(sums, out_sums, out=np.ones_like(sums), where=out_sums != 0)
    k_out = k_out * scale
    H_out = translation(c_safe) @ Hb
    if single:
        return H_out[0], k_out[0], c[0]
    return H_out, k_out, c


def shift_pair(latent: np.ndarray, kernel: np.ndarray, delta: tuple[int, int]
               ) -> tuple[np.ndarray, np.ndarray]:
    """The translational ambiguity: ``L'(x) = L(x - delta)``, ``k'(d) = k(d + delta)``.

    Then ``k' * L' = k * L`` (paper, *Translational Ambiguity in Deconvolution*). The latent image
    is shifted periodically (``np.roll``), the kernel with zero fill; the identity holds exactly
    for periodic convolution when no kernel weight leaves the window.

    Args:
        latent: ``(h, w)`` image; kernel: ``(K, K)``; delta: integer ``(dx, dy)`` px.
    Returns:
        ``(L', k')``.
    Raises:
        ValueError: the shift would push kernel weight out of its window.
    """
    dx, dy = int(delta[0]), int(delta[1])
    k = np.asarray(kernel)
    K = k.shape[0]
    shifted = np.zeros_like(k)
    src = k[max(dy, 0):K + min(dy, 0), max(dx, 0):K + min(dx, 0)]
    if not np.isclose(np.abs(src).sum(), np.abs(k).sum()):
        raise ValueError(f"shift {delta} pushes kernel weight out of the {K} x {K} window")
    shifted[max(-dy, 0):K - max(dy, 0), max(-dx, 0):K - max(dx, 0)] = src
    return np.roll(np.asarray(latent), (dy, dx), axis=(0, 1)), shifted
