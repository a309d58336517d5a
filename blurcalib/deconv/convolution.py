"""Valid convolution of latent images with PSF kernels, direct or by FFT."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar, cast

import torch
import torch.nn.functional as nnf

DIRECT_PER_FFT_POINT = 300.0
"""Multiply-adds of a direct convolution that cost as much as one point of an FFT convolution
(forward and inverse transforms): on one CPU thread a depthwise ``conv2d`` runs at ~0.03 ns per
multiply-add and the FFT at 7-10 ns per point of its grid (9 channels of 7-24 blocks, kernels
of 13-51 px, grids of 50-144 px)."""


_P = ParamSpec("_P")
_R = TypeVar("_R")

_DENORMAL = 1e-39
"""A float32 denormal (below 1.18e-38)."""


def flushing_denormals() -> bool:
    """Whether the calling thread flushes denormal floats to zero."""
    return float(torch.tensor([_DENORMAL], dtype=torch.float32)[0] * 1.0) == 0.0


def denormals_flushed(func: Callable[_P, _R]) -> Callable[_P, _R]:
    """Run ``func`` with denormal floats flushed to zero in the calling thread (x86 FTZ/DAZ,
    ``torch.set_flush_denormal``), and give the thread its own setting back after it. The block
    solver, the field fit and the extraction of a frame run so.

    A float32 kernel cast from the float64 kernel solve can hold entries below 1.2e-38, and each
    multiply-add of the direct convolution with one runs through the CPU's slow path
    (docs/decisions/denormals-flushed.md). Values that small are zero for grey levels; other code
    of the thread (a float64 round trip of the smallest doubles) may need them, hence the restore.
    """
    @functools.wraps(func)
    def run(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        if flushing_denormals():
            return func(*args, **kwargs)
        torch.set_flush_denormal(True)
        try:
            return func(*args, **kwargs)
        finally:
            torch.set_flush_denormal(False)

    return run


def fft_size(n: int) -> int:
    """The smallest ``2^a 3^b 5^c >= n``."""
    best = 1 << max(n - 1, 0).bit_length()
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            m = p35
            while m < n:
                m *= 2
            best = min(best, m)
            p35 *= 3
        p5 *= 5
    return best


def fft_grid(latent: tuple[int, int], K: int) -> tuple[int, int] | None:
    """The FFT grid ``(rows, cols)`` of a valid convolution of ``latent = (Hl, Wl)`` px channels
    with ``K x K`` kernels, or None where the direct convolution is cheaper: its ``h w K^2``
    multiply-adds per channel (``h = Hl - K + 1``, ``w`` alike) cost less than the FFT's grid
    (:data:`DIRECT_PER_FFT_POINT`)."""
    Hl, Wl = latent
    size = (fft_size(Hl), fft_size(Wl))
    direct = (Hl - K + 1) * (Wl - K + 1) * K * K <= DIRECT_PER_FFT_POINT * size[0] * size[1]
    return None if direct else size


def kernel_spectrum(k: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
    """The transform of kernels ``k (b, K, K)`` or ``(b, C, K, K)`` on an FFT ``grid``
    (:func:`fft_grid`), ``(b, 1 or C, rows, cols // 2 + 1)``, for :func:`valid_convolution`."""
    return cast(torch.Tensor, torch.fft.rfft2(k[:, None] if k.ndim == 3 else k, s=grid))


def latent_spectrum(L: torch.Tensor, K: int) -> torch.Tensor | None:
    """The transform of latent channels ``L (b, C, Hl, Wl)`` on the FFT grid of their valid
    convolution with ``K x K`` kernels (:func:`fft_grid`), ``(b, C, rows, cols // 2 + 1)``, for
    :func:`valid_convolution`; None where that convolution is direct."""
    grid = fft_grid((L.shape[-2], L.shape[-1]), K)
    return None if grid is None else torch.fft.rfft2(L, s=grid)


def valid_convolution(L: torch.Tensor, k: torch.Tensor, spectrum: torch.Tensor | None = None,
                      latent: torch.Tensor | None = None) -> torch.Tensor:
    """Valid convolution ``(k * L)`` of latent channels ``L (b, C, Hl, Wl)`` -> ``(b, C, h, w)``,
    ``h = Hl - 2c``, ``w = Wl - 2c`` (``c`` the kernel radius).

    ``k`` is ``(b, K, K)`` (one kernel for every channel of a block) or ``(b, C, K, K)`` (one
    per channel; ``L`` may then have one channel, shared); ``spectrum`` its
    :func:`kernel_spectrum` and ``latent`` ``L``'s :func:`latent_spectrum` when computed already
    (kernels held through several convolutions, latent channels convolved with several kernels).
    Direct where :func:`fft_grid` says so: one depthwise ``conv2d`` over the ``b C`` channels (a
    correlation, so with the kernel flipped). Otherwise circular FFT convolution on a grid of at
    least ``(Hl, Wl)`` (5-smooth sides, the fast FFT sizes): the wrap-around only reaches the
    first ``2c`` rows and columns, outside the output.
    """
    k = k[:, None] if k.ndim == 3 else k
    b, C = L.shape[0], max(L.shape[1], k.shape[1])
    Hl, Wl = L.shape[-2:]
    K = k.shape[-1]
    r2 = K - 1
    h, w = Hl - r2, Wl - r2
    grid = fft_grid((Hl, Wl), K)
    if grid is None:
        weight = k.flip(-2, -1).expand(b, C, K, K).reshape(b * C, 1, K, K)
        L = L.expand(b, C, Hl, Wl)
        out = nnf.conv2d(L.reshape(1, b * C, Hl, Wl), weight, groups=b * C)
        return out.reshape(b, C, h, w)
    kf = kernel_spectrum(k, grid) if spectrum is None else spectrum
    lf = torch.fft.rfft2(L, s=grid) if latent is None else latent
    out = torch.fft.irfft2(lf * kf, s=grid)
    return cast(torch.Tensor, out[..., r2:r2 + h, r2:r2 + w])
