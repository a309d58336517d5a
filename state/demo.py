"""The translational ambiguity of deconvolution, as a teaching demo.

A blurred star ``k * L`` is explained equally well by the latent star shifted by ``delta`` and the
kernel shifted by ``-delta`` (:func:`blurcalib.deconv.shift_pair`): ``k' * L' = k * L``. The
image cannot tell where the star "really" is; only a convention can (the PSF's centroid at the
kernel centre) and the target's geometry (neighbouring blocks share corners; one camera model
explains every frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from blurcalib.deconv import shift_pair
from blurcalib.pattern import star_sector_white
from blurcalib.synth import splat

TILE_PX = 64
"""Side of the demo's latent tile (px): two squares of 32 px, so the tile is periodic."""
KERNEL_SIZE = 17
MAX_SHIFT = 4
"""Largest ``|delta|`` per axis (px) that keeps the demo kernel inside its window."""


def star_tile(num_segments: int, size: int = TILE_PX, supersample: int = 4) -> np.ndarray:
    """A periodic latent image ``(size, size)`` in 0..1: stars on a grid of ``size / 2`` px
    squares, a star centre at pixel ``(size / 2, size / 2)``."""
    square = size / 2.0
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    j = np.arange(size, dtype=np.float64)
    acc = np.zeros((size, size))
    for oy in offs:
        for ox in offs:
            x = (j[None, :] + ox - size / 2.0) / square
            y = (j[:, None] + oy - size / 2.0) / square
            acc += star_sector_white(x - np.round(x), y - np.round(y), num_segments)
    return acc / supersample**2


def motion_kernel(size: int = KERNEL_SIZE, length: float = 7.0, bend: float = 2.0) -> np.ndarray:
    """A curved motion-blur kernel ``(size, size)`` summing to 1 (a hand-shake arc)."""
    t = np.linspace(-0.5, 0.5, 64)
    offsets = np.column_stack([length * t, bend * (4.0 * t**2 - 1.0 / 3.0)])
    return splat(offsets, size)


def periodic_blur(latent: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``(k * L)(x) = sum_d k(d) L(x - d)`` with ``L`` periodic (via the FFT)."""
    h, w = latent.shape
    c = (kernel.shape[0] - 1) // 2
    wrapped = np.zeros((h, w))
    for i in range(kernel.shape[0]):
        for j in range(kernel.shape[1]):
            wrapped[(i - c) % h, (j - c) % w] += kernel[i, j]
    return np.real(np.fft.ifft2(np.fft.fft2(latent) * np.fft.fft2(wrapped)))


def kernel_centroid(kernel: np.ndarray) -> np.ndarray:
    """``(2,)`` px ``(x, y)``: the kernel's centroid relative to its centre."""
    c = (kernel.shape[0] - 1) / 2.0
    yy, xx = np.mgrid[0:kernel.shape[0], 0:kernel.shape[1]]
    total = kernel.sum()
    return np.array([(kernel * (xx - c)).sum() / total, (kernel * (yy - c)).sum() / total])


@dataclass(frozen=True)
class AmbiguityDemo:
    """One setting of the demo.

    Attributes:
        delta: ``(dx, dy)`` px.
        latent: ``L'``, the latent tile shifted by ``delta``.
        kernel: ``k'``, the kernel shifted by ``-delta``.
        blurred: ``k' * L'``.
        residual: ``k' * L' - k * L`` (zero up to rounding).
        star_centre: ``(2,)`` px, where ``L'`` puts the star centre.
        centroid: ``(2,)`` px, ``k'``'s centroid relative to the kernel centre.
    """

    delta: tuple[int, int]
    latent: np.ndarray
    kernel: np.ndarray
    blurred: np.ndarray
    residual: np.ndarray
    star_centre: np.ndarray
    centroid: np.ndarray


def ambiguity_demo(delta: tuple[int, int], num_segments: int = 16) -> AmbiguityDemo:
    """The latent star shifted by ``delta`` and the kernel by ``-delta``: the same blurred image."""
    latent = star_tile(num_segments)
    kernel = motion_kernel()
    reference = periodic_blur(latent, kernel)
    shifted, k_shifted = shift_pair(latent, kernel, delta)
    blurred = periodic_blur(shifted, k_shifted)
    centre = np.array([TILE_PX / 2.0 + delta[0], TILE_PX / 2.0 + delta[1]])
    return AmbiguityDemo((int(delta[0]), int(delta[1])), shifted, k_shifted, blurred, blurred - reference,
                         centre, kernel_centroid(k_shifted))
