"""Valid convolution of latent images with PSF kernels, direct or by FFT."""

from __future__ import annotations

import torch
import torch.nn.functional as nnf

DIRECT_CONV_MAX_KERNEL = 29
"""Largest kernel side (px) convolved directly rather than by FFT: on one CPU thread the direct
(depthwise) convolution of the 9 Jacobian channels takes 0.28x the FFT's time at 7 px, 0.44x at
19 px and 0.7x at 29 px; at 31 px the FFT is faster (``docs/deconvolution.md``)."""


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


def valid_convolution(L: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """Valid convolution ``(k * L)`` of latent channels ``L (b, C, Hl, Wl)`` -> ``(b, C, h, w)``,
    ``h = Hl - 2c``, ``w = Wl - 2c`` (``c`` the kernel radius).

    ``k`` is ``(b, K, K)`` (one kernel for every channel of a block) or ``(b, C, K, K)`` (one
    per channel; ``L`` may then have one channel, shared). Kernels up to
    :data:`DIRECT_CONV_MAX_KERNEL` px: direct, as one depthwise ``conv2d`` over the ``b C``
    channels (a correlation, so with the kernel flipped). Larger: circular FFT convolution on
    a grid of at least ``(Hl, Wl)`` (5-smooth sides, the fast FFT sizes): the wrap-around only
    reaches the first ``2c`` rows and columns, outside the output.
    """
    k = k[:, None] if k.ndim == 3 else k
    b, C = L.shape[0], max(L.shape[1], k.shape[1])
    Hl, Wl = L.shape[-2:]
    K = k.shape[-1]
    r2 = K - 1
    h, w = Hl - r2, Wl - r2
    if K <= DIRECT_CONV_MAX_KERNEL:
        weight = k.flip(-2, -1).expand(b, C, K, K).reshape(b * C, 1, K, K)
        L = L.expand(b, C, Hl, Wl)
        out = nnf.conv2d(L.reshape(1, b * C, Hl, Wl), weight, groups=b * C)
        return out.reshape(b, C, h, w)
    size = (fft_size(Hl), fft_size(Wl))
    kf = torch.fft.rfft2(k, s=size)
    out = torch.fft.irfft2(torch.fft.rfft2(L, s=size) * kf, s=size)
    return out[..., r2:r2 + h, r2:r2 + w]
